"""Plumbing and plain maths that every layer stands on.

Errors (one line, exit 2), atomic file writes and safetensors (``io``), restricted loading of other people's
files (``safe_load``), input checks (``checks``), devices and the Warp <-> torch bridge (``device``), the count
of host syncs (``host_reads``), Mitsuba's variant (``mitsuba_variant``), rotations and skeletons (``geometry``),
pinhole cameras (``cameras``) and CLIP weights on disk (``weights``).

May import: nothing else in the package.
"""
