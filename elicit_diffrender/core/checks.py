"""Checks of what the user hands in: images, masks, numeric fields and command-line numbers.

Every failure is an :class:`InputError` (or the caller's error class) whose one line names the
file or field and says what was expected.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from .errors import ElicitError

MAX_MEGAPIXELS = 40.0  # default size guard for photos and images (a 40 MP photo needs about 1 GB as float)


class InputError(ElicitError):
    """An input file or value that cannot be used."""


def safe_name(name: object, where: str, error: type[ElicitError] = InputError) -> str:
    """``name`` as one plain path component (a job, camera or file name that data gives): a non-empty string
    with no path separator, no NUL and not ``.`` or ``..``, so that ``folder / name`` stays in ``folder``."""
    if not isinstance(name, str) or name in ("", ".", "..") or len(name) > 255 or any(c in name for c in "/\\\0"):
        raise error(f"{where}: {name!r} is not a plain name (no path separator, not '.' or '..', at most 255 long)")
    return name


def inside(folder: Path, relative: str | Path, where: str, error: type[ElicitError] = InputError) -> Path:
    """``folder / relative``, resolved, when it lies inside ``folder`` (symbolic links followed); else one
    ``error`` naming ``where``: a path from data never reaches outside the folder it belongs to."""
    root = Path(folder).resolve()
    path = (root / relative).resolve()
    if path == root or root not in path.parents:
        raise error(f"{where}: {str(relative)!r} leads outside {folder}")
    return path


def numeric(value, where: str, shape: tuple[int, ...] | None = None, error: type[ElicitError] = InputError):
    """``value`` as a finite float64 array of ``shape`` (-1: any length on that axis). ``where`` names the
    field, as in "motion.npz field 'pose'"."""
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError):  # ragged nested lists
        raise error(f"{where} must be an array of numbers, got a ragged or mixed value") from None
    if arr.dtype.kind not in "biuf":
        raise error(f"{where} must hold numbers, got {arr.dtype} values")
    arr = arr.astype(np.float64)
    if shape is not None and (
        arr.ndim != len(shape) or any(s not in (-1, n) for s, n in zip(shape, arr.shape, strict=True))
    ):
        wanted = "(" + ", ".join("N" if s == -1 else str(s) for s in shape) + ")"
        raise error(f"{where} must be {wanted}, got {tuple(arr.shape)}")
    if not np.isfinite(arr).all():
        raise error(f"{where} contains NaN or infinite values")
    return arr


def _decode(path: Path, what: str, expect_hw, max_megapixels: float, error) -> tuple[np.ndarray, float]:
    """An image file's pixels and their full-scale value (1 for 1-bit, 255 for 8-bit, 65535 for 16-bit);
    its size is checked before anything is decoded (this check replaces Pillow's own, which would end in a
    traceback), and its EXIF orientation is applied, as every photo viewer does."""
    from PIL import Image, ImageOps, UnidentifiedImageError

    if not path.is_file():
        raise error(f"{path}: {what} not found")
    limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
    try:
        img = Image.open(path)
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise error(f"{path}: unreadable {what} ({exc})") from None
    finally:
        Image.MAX_IMAGE_PIXELS = limit
    megapixels = img.width * img.height / 1e6
    if megapixels > max_megapixels:
        raise error(
            f"{path}: {what} is {img.width}x{img.height} ({megapixels:.0f} MP), above the {max_megapixels:g} MP "
            "limit; shrink it, or raise the limit with --max-megapixels"
        )
    try:
        img = ImageOps.exif_transpose(img)
    except (OSError, ValueError, SyntaxError) as exc:  # a damaged EXIF block or pixel data
        raise error(f"{path}: unreadable {what} ({exc})") from None
    if expect_hw is not None and (img.height, img.width) != tuple(expect_hw):
        raise error(
            f"{path}: {what} is {img.width}x{img.height}, expected {expect_hw[1]}x{expect_hw[0]} "
            "(the camera's width x height)"
        )
    try:
        mode = img.mode
        if mode == "1":
            return np.asarray(img, dtype=bool).astype(np.uint8), 1.0
        if mode.startswith("I;16") or mode == "I":
            return np.asarray(img).astype(np.float64), 65535.0
        if mode == "F":
            return np.asarray(img, dtype=np.float64), 1.0
        if mode not in ("L", "LA", "RGB", "RGBA"):
            img = img.convert("RGBA" if "A" in mode or "transparency" in img.info else "RGB")
        return np.asarray(img), 255.0
    except (OSError, ValueError) as exc:
        raise error(f"{path}: unreadable {what} ({exc})") from None


def read_image(
    path: str | Path,
    what: str = "image",
    expect_hw: tuple[int, int] | None = None,
    max_megapixels: float = MAX_MEGAPIXELS,
    error: type[ElicitError] = InputError,
) -> tuple[np.ndarray, np.ndarray | None]:
    """An image file as (H, W, 3) float32 RGB in [0, 1] and its (H, W) alpha in [0, 1] (None without one).

    Grey, grey + alpha, palette, RGB and RGBA at 1, 8 or 16 bits per channel are read at their own scale.
    """
    pixels, full = _decode(Path(path), what, expect_hw, max_megapixels, error)
    x = pixels.astype(np.float32) / np.float32(full)
    if x.ndim == 2:
        x = x[..., None]
    channels = x.shape[2]
    alpha = x[..., -1] if channels in (2, 4) else None
    rgb = x[..., :1].repeat(3, axis=2) if channels <= 2 else x[..., :3]
    return np.clip(rgb, 0.0, 1.0), None if alpha is None else np.clip(alpha, 0.0, 1.0)


def read_mask(
    path: str | Path,
    what: str = "mask",
    expect_hw: tuple[int, int] | None = None,
    max_megapixels: float = MAX_MEGAPIXELS,
    error: type[ElicitError] = InputError,
) -> np.ndarray:
    """A mask file as (H, W) bool: above half of full scale (1-, 8- or 16-bit; the first channel of colour)."""
    pixels, full = _decode(Path(path), what, expect_hw, max_megapixels, error)
    if pixels.ndim == 3:
        pixels = pixels[..., 0]
    return pixels.astype(np.float64) > full / 2


# ---- command-line numbers (argparse types: a bad value is one line naming the option) ----------------------
def positive_int(raw: str) -> int:
    try:
        value = int(raw)
    except ValueError:
        value = 0
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {raw!r}")
    return value


def positive_float(raw: str) -> float:
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {raw!r}")
    return value


def int_between(lo: int, hi: int):
    """An argparse type: an integer in [lo, hi] (a bound keeps the work a number implies within memory and time)."""

    def parse(raw: str) -> int:
        try:
            value = int(raw)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer, got {raw!r}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be an integer in [{lo}, {hi}], got {raw!r}")
        return value

    return parse


def float_between(lo: float, hi: float):
    """An argparse type: a finite number in [lo, hi]."""

    def parse(raw: str) -> float:
        try:
            value = float(raw)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and lo <= value <= hi):
            raise argparse.ArgumentTypeError(f"must be a number in [{lo:g}, {hi:g}], got {raw!r}")
        return value

    return parse


def unit_fraction(raw: str) -> float:
    value = positive_float(raw)
    if value > 1:
        raise argparse.ArgumentTypeError(f"must be in (0, 1], got {raw!r}")
    return value
