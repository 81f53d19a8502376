"""Atomic writes: every file is written beside its target and renamed into place, whole folders too;
and safetensors files of tensors with a JSON header, which cannot carry code."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ElicitError

_UMASK = os.umask(0)
os.umask(_UMASK)


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp_path)`` then rename the temporary file onto ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600 files; give them the usual permissions
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) or type(exc).__name__ == "SafetensorError":  # a full disk, a read-only folder
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc).splitlines()[0][:200]
            raise ElicitError(f"{path}: cannot write ({reason})") from None
        raise
    return path


def is_empty_folder(path: Path) -> bool:
    return not path.exists() or (path.is_dir() and not any(path.iterdir()))


@contextmanager
def folder_in_place(path: str | Path, force: bool = False) -> Iterator[Path]:
    """Write a whole folder: fill the temporary sibling this yields; when the block ends without an
    error, it replaces ``path``. On any error (a full disk, a bad input found late) the temporary folder
    is removed and ``path`` is left as it was. A non-empty ``path`` is replaced only with ``force``.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ElicitError(f"{path}: exists and is not a folder")
    if not force and not is_empty_folder(path):
        raise ElicitError(f"{path}: folder exists and is not empty; pass --force to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    for stale in path.parent.glob(f".{path.name}.*.partial"):  # left by a killed earlier write
        shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_UMASK)
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            os.replace(path, old / path.name)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


MAX_JSON_BYTES = 64 * 2**20  # a subject's, run's or job's JSON file is a few kilobytes


def parse_json(text: str | bytes, where: str, error: type[ElicitError] = ElicitError) -> Any:
    """JSON text (bytes must be UTF-8) as Python values; invalid UTF-8, bad syntax, nesting too deep for the
    parser and integers of more digits than Python converts are each one ``error`` naming ``where``."""
    try:
        if isinstance(text, bytes):
            text = text.decode("utf-8")
        return json.loads(text)
    except UnicodeDecodeError as exc:
        raise error(f"{where}: not UTF-8 text (byte {exc.start})") from None
    except RecursionError:
        raise error(f"{where}: not valid JSON (nested too deep)") from None
    except ValueError as exc:  # JSONDecodeError, and the digit limit on integers
        raise error(f"{where}: not valid JSON ({exc})") from None


def read_json(path: str | Path, error: type[ElicitError] = ElicitError) -> Any:
    """A JSON file's values (see :func:`parse_json`); a missing, unreadable or oversized file is one ``error``."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_JSON_BYTES:
            raise error(f"{path}: {size} bytes, more than a JSON file here may hold ({MAX_JSON_BYTES})")
        data = path.read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror or exc})") from None
    return parse_json(data, str(path), error)


def write_text(path: str | Path, text: str) -> Path:
    return atomic_write(path, lambda p: p.write_text(text))


def write_json(path: str | Path, data: Any) -> Path:
    return write_text(path, json.dumps(data, indent=2, default=_json_default) + "\n")


def write_image(path: str | Path, image: np.ndarray) -> Path:
    """Save an (H, W[, C]) image: float in [0, 1] or uint8."""
    import imageio.v3 as iio

    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return atomic_write(path, lambda p: iio.imwrite(p, img, extension=Path(path).suffix))


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot serialise {type(obj).__name__} to JSON")


# ---- tensors with JSON: safetensors files that cannot carry code -------------------------------------------
TENSOR_REF = "__tensor__"
META_KEY = "elicit"


def split_tensors(tree: Any, prefix: str = "") -> tuple[Any, dict]:
    """Replace every torch tensor in a tree of dicts (string keys) and lists by ``{TENSOR_REF: name}``.

    Returns the JSON-able rest of the tree and the tensors by name (names are the paths, joined by '/').
    """
    import torch

    if isinstance(tree, torch.Tensor):
        return {TENSOR_REF: prefix}, {prefix: tree}
    tensors: dict = {}
    if isinstance(tree, dict):
        out = {}
        for key, value in tree.items():
            if not isinstance(key, str):
                raise TypeError(f"{prefix}: keys must be strings, got {key!r}")
            out[key], found = split_tensors(value, f"{prefix}/{key}" if prefix else key)
            tensors.update(found)
        return out, tensors
    if isinstance(tree, (list, tuple)):
        out_list = []
        for i, value in enumerate(tree):
            item, found = split_tensors(value, f"{prefix}/{i}")
            out_list.append(item)
            tensors.update(found)
        return out_list, tensors
    return tree, tensors


def join_tensors(tree: Any, tensors: dict) -> Any:
    """Inverse of :func:`split_tensors`; a reference to a missing tensor raises ``KeyError``."""
    if isinstance(tree, dict):
        if set(tree) == {TENSOR_REF}:
            return tensors[tree[TENSOR_REF]]
        return {k: join_tensors(v, tensors) for k, v in tree.items()}
    if isinstance(tree, list):
        return [join_tensors(v, tensors) for v in tree]
    return tree


def write_tensors(path: str | Path, tree: Any) -> Path:
    """Write a tree of tensors, numbers, strings, lists and dicts as one safetensors file (the rest as
    JSON in its header), atomically."""
    from safetensors.torch import save_file

    rest, tensors = split_tensors(tree)
    tensors = {k: v.detach().cpu().contiguous().clone() for k, v in tensors.items()}
    header = {META_KEY: json.dumps(rest, default=_json_default)}
    return atomic_write(path, lambda p: save_file(tensors, str(p), metadata=header))


def read_tensors(path: str | Path) -> Any:
    """Read a file written by :func:`write_tensors` (never runs code). Raises ``ValueError`` for a file
    that is not one."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            header = (f.metadata() or {}).get(META_KEY)
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, OSError) as exc:
        raise ValueError(f"not a safetensors file ({exc})") from None
    if header is None:
        raise ValueError("a safetensors file without elicit's header")
    try:
        return join_tensors(parse_json(header, "header", ElicitError), tensors)
    except (ValueError, KeyError, TypeError) as exc:  # ElicitError is a ValueError
        raise ValueError(f"damaged header ({type(exc).__name__}: {exc})") from None
