"""Reading files that other people made without running their code: numpy files and pickles, restricted.

A pickle can call any function while it loads, so a crafted ``.npy``, ``.npz`` or ``.pkl`` runs
code the moment numpy (with pickles allowed) or ``pickle.load`` opens it. Here:

* ``.npz``/``.npy`` files of plain arrays load with ``allow_pickle=False``;
* formats that are pickles by nature (ZJU-MoCap's ``annots.npy``, EasyMocap's ``new_params/*.npy``,
  SMPL ``.pkl`` model files) go through :class:`RestrictedUnpickler`, which builds numpy arrays,
  numpy scalars, scipy sparse matrices, dicts, lists, tuples, strings and numbers, and refuses every
  other global with an :class:`UnsafeFileError` naming the file and what it asked for.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ElicitError

# (module, name) pairs a pickle of arrays and containers needs, and nothing else.
_NUMPY = {
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "scalar"),
    ("_codecs", "encode"),  # bytes in protocol-2 pickles (Python 2 era files such as SMPL's)
}
_SPARSE = {"csc_matrix", "csr_matrix", "coo_matrix"}


class UnsafeFileError(ElicitError):
    """A file that would run code (or is not what it claims to be) when loaded."""


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that only builds arrays, sparse matrices, containers, strings and numbers."""

    def __init__(self, file, path: Path, error: type[ElicitError] = UnsafeFileError) -> None:
        super().__init__(file, encoding="latin1")
        self.path, self.error = path, error

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _NUMPY or (module.split(".")[:2] == ["scipy", "sparse"] and name in _SPARSE):
            return super().find_class(module, name)
        raise self.error(
            f"{self.path}: refused: it asks to run {module}.{name} while loading (only arrays, numbers, "
            "strings, lists and dicts are read from pickled files)"
        )


PICKLE_ERRORS = (OSError, EOFError, pickle.UnpicklingError, ValueError, TypeError, AttributeError, IndexError)


def load_pickle(path: str | Path, error: type[ElicitError] = UnsafeFileError) -> Any:
    """A pickled file (for example an SMPL ``.pkl``) through :class:`RestrictedUnpickler`; every problem
    is an ``error`` naming the file."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return RestrictedUnpickler(f, path, error).load()
    except PICKLE_ERRORS as exc:
        raise error(f"{path}: not a readable pickle ({type(exc).__name__}: {exc})") from None


def load_npy(path: str | Path, error: type[ElicitError] = UnsafeFileError) -> Any:
    """A ``.npy`` file: plain arrays as they are; an object array (a pickle inside) through the restricted
    unpickler, returned as its single object when it holds one (``np.save(path, some_dict)``)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            fmt = np.lib.format
            version = fmt.read_magic(f)
            read_header = {(1, 0): fmt.read_array_header_1_0, (2, 0): fmt.read_array_header_2_0}.get(version)
            if read_header is None:
                raise ValueError(f"unsupported .npy format version {version}")
            _, _, dtype = read_header(f)
            if not dtype.hasobject:
                f.seek(0)
                return np.load(f, allow_pickle=False)
            array = RestrictedUnpickler(f, path, error).load()
    except PICKLE_ERRORS as exc:
        raise error(f"{path}: not a readable .npy file ({type(exc).__name__}: {exc})") from None
    if not isinstance(array, np.ndarray):
        raise error(f"{path}: not a readable .npy file (it holds a {type(array).__name__})")
    return array.item() if array.shape == () else array


class NpzFields(dict):
    """An ``.npz`` file's arrays by name. A field that holds pickled Python objects is never unpickled:
    reading it raises :class:`UnsafeFileError`, and the other fields stay usable."""

    def __init__(self, path: Path, arrays: dict[str, np.ndarray], pickled: list[str], error: type[ElicitError]):
        super().__init__(arrays)
        self.path, self.pickled, self.error = path, set(pickled), error
        for key in pickled:
            super().__setitem__(key, None)

    def __getitem__(self, key: str) -> np.ndarray:
        if key in self.pickled:
            raise self.error(f"{self.path}: refused: field {key!r} holds pickled Python objects, which could run code")
        return super().__getitem__(key)

    def get(self, key: str, default=None):
        return self[key] if key in self else default


def load_npz(path: str | Path, error: type[ElicitError] = UnsafeFileError) -> NpzFields:
    """The arrays of an ``.npz`` file, read with pickles disallowed (see :class:`NpzFields`); every problem
    is an ``error`` naming the file."""
    path = Path(path)
    arrays, pickled = {}, []
    try:
        with np.load(path, allow_pickle=False) as data:
            for key in data.files:
                try:
                    arrays[key] = data[key]
                except ValueError:  # "Object arrays cannot be loaded when allow_pickle=False"
                    pickled.append(key)
    except Exception as exc:  # numpy raises several types for corrupt or foreign files
        raise error(f"{path}: not a readable .npz file ({type(exc).__name__}: {exc})") from None
    return NpzFields(path, arrays, pickled, error)
