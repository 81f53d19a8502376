"""ELICIT: one-shot animatable avatars from a single photo, with Warp kernels and Mitsuba 3 renders."""

__version__ = "0.1.0"
