"""What a user or a benchmark script runs: ``cli`` (the ``elicit`` command), ``demo``, ``batch`` (many avatars on
Ray) and ``benchtools`` (shared helpers of ``scripts/bench_*.py``).

May import: every layer. Nothing in the package imports it.
"""
