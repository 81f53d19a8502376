"""The fitted models and the operators that render and score them.

``field`` (the canonical radiance and motion-weight grids), ``avatar`` (the grid warped to a pose and rendered),
``volume`` and ``skinning`` (the Warp ray marcher and inverse-LBS warp, with their adjoints), ``total_variation``,
``torch_reference`` (pure-torch twins of the kernels, for tests and benchmarks), ``textured_body`` (the paper's
explicit-texture baseline), ``load`` (either model from a run folder), ``losses`` (image losses and metrics) and
``encoders`` (CLIP and its weights-free fallback).

May import: ``data``, ``body``, ``core``, and ``kernels`` (the only layer that does).
"""
