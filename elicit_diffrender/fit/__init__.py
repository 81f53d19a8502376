"""``elicit fit``: ELICIT's one-shot optimisation of an avatar (or the paper's textured-body baseline).

Modules, one job each: ``config`` (the flat ``FitConfig``, presets, overrides), ``run`` (the run folder and
the entry point ``fit``), ``views`` (what the fit looks at), ``hybrid_sampling`` (the paper's part- and
rotation-aware novel views), ``render`` (the avatar at the training poses), ``objective`` (the loss terms and
their weights), ``completion`` (the weights-free semantic fallback), ``shading``, ``room`` (density beyond the
body), ``regions`` (regulariser blocks), ``guard`` (empty-render recovery), ``checkpoint`` (resumable state),
``streams`` (random generators), ``trainer`` (the loop) and ``baseline`` (the explicit-texture fit). A run folder
holds ``checkpoint.safetensors`` (resumable), ``avatar.safetensors`` (the result), ``run.json``, ``log.txt`` and
``previews/``.

May import: ``model``, ``data``, ``body``, ``core``. Not ``inputs`` or ``outputs`` (siblings).
"""
