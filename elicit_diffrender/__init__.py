"""ELICIT: one-shot animatable avatars from a single photo, with Warp kernels and Mitsuba 3 renders."""

import os

# torch's OpenMP threads spin while they wait for work, taking the cores from Warp's launch threads
# and from any other process on the machine (two fits side by side then slow each other down far
# beyond their share). Passive waiting avoids that. It must be set before torch (libgomp) starts;
# a value the user set wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
