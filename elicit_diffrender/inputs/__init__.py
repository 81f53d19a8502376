"""What makes an ``elicit-subject/1`` folder: ``prepare`` (one photo), ``importers`` (ELICIT's in-the-wild
layout, ZJU-MoCap) and ``synth`` (synthetic clothed people); ``mediapipe_bridge`` runs ``mediapipe_runner`` in its
own environment (masks and keypoints for ``prepare``).

May import: ``model``, ``data``, ``body``, ``core``. Not ``fit`` or ``outputs`` (siblings).
"""
