"""Mitsuba 3, imported once with the variant this machine can run: ``cuda_ad_rgb`` with a GPU, else ``llvm_ad_rgb``."""

from __future__ import annotations

import glob
import os

from .errors import ElicitError

_LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/aarch64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/llvm-19/lib/libLLVM.so.19.1",
)
_MI = None


class MitsubaError(ElicitError):
    """Mitsuba cannot run here."""


def mitsuba():
    """Import Mitsuba with the right variant: ``cuda_ad_rgb`` with a GPU, else ``llvm_ad_rgb``.

    Points Dr.Jit at LLVM 19 first (``DRJIT_LIBLLVM_PATH``); the system's LLVM 15 crashes it.
    """
    global _MI
    if _MI is not None:
        return _MI
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        found = [p for p in _LLVM_CANDIDATES if os.path.exists(p)] + sorted(glob.glob("/usr/lib/*/libLLVM.so.19*"))
        if found:
            os.environ["DRJIT_LIBLLVM_PATH"] = found[0]
    import drjit as dr  # noqa: F401  (imported after the environment is set)
    import mitsuba as mi

    want = os.environ.get("ELICIT_MITSUBA_VARIANT")
    if want is None:
        import torch

        want = "cuda_ad_rgb" if torch.cuda.is_available() and "cuda_ad_rgb" in mi.variants() else "llvm_ad_rgb"
    try:
        mi.set_variant(want)
    except Exception as exc:  # Mitsuba raises plain exceptions when a backend is missing
        raise MitsubaError(
            f"Mitsuba variant {want!r} is unavailable ({exc}). The LLVM backend needs libLLVM 19: run "
            f"scripts/setup.sh or 'apt-get install libllvm19' (DRJIT_LIBLLVM_PATH="
            f"{os.environ.get('DRJIT_LIBLLVM_PATH')!r})"
        ) from exc
    _MI = mi
    return mi
