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

# What a pickle of arrays and containers may name, each read by a stand-in of this module's (below) that checks the
# state it is given before it builds anything: numpy's own reconstructors never see pickled state.
_RECONSTRUCT = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct")}
_SCALAR = {("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar")}
_FROMBUFFER = {("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer")}
_SPARSE = {"csc_matrix", "csr_matrix", "coo_matrix"}
# Plain dtypes an array may have (any byte order); fixed-width strings up to MAX_STRING characters; "O" only for
# the object arrays (lists of other pickled values) that ``np.save`` writes around a dict.
_PLAIN_DTYPES = {"b1", "i1", "i2", "i4", "i8", "u1", "u2", "u4", "u8", "f2", "f4", "f8", "c8", "c16", "O"}
MAX_STRING = 4096
MAX_ELEMENTS = 200_000_000  # array elements in one file
MAX_ITEMS = 2_000_000  # strings, numbers, lists and dicts in one file, counted as a tree (a ZJU annots file: ~50k)
MAX_DEPTH = 64  # containers nested in containers


class UnsafeFileError(ElicitError):
    """A file that would run code (or is not what it claims to be) when loaded."""


class _Refused(ValueError):
    """Pickled state that a stand-in will not build from."""


def _dtype_code(code: object) -> str:
    if isinstance(code, bytes):
        code = code.decode("latin1")
    if not isinstance(code, str):
        raise _Refused(f"a dtype named by a {type(code).__name__}")
    plain = code.lstrip("<>|=")
    if plain in _PLAIN_DTYPES:
        return code
    if plain[:1] == "O" and plain[1:] in ("4", "8"):  # object arrays name their pointer size
        return "O"
    if plain[:1] in ("U", "S") and plain[1:].isdigit() and int(plain[1:]) <= MAX_STRING:
        return code
    raise _Refused(f"dtype {code!r} (only numbers, booleans and short strings are read)")


class _Dtype:
    """Stands for ``numpy.dtype(code, align, copy)``; its pickled state may only set the byte order."""

    def __init__(self, code: object = "f8", *args: object) -> None:
        self.code, self.order = _dtype_code(code), ""

    def __setstate__(self, state: object) -> None:
        if not isinstance(state, tuple) or len(state) < 2 or state[1] not in ("<", ">", "|", "="):
            raise _Refused("a dtype's state")
        if any(field is not None for field in state[2:5]):
            raise _Refused("a structured dtype")
        self.order = "" if state[1] in ("|", "=") else state[1]

    def build(self) -> np.dtype:
        code = self.code if self.code[:1] in "<>|=" else self.order + self.code
        return np.dtype(code)


def _as_dtype(value: object) -> np.dtype:
    if not isinstance(value, _Dtype):
        raise _Refused(f"a dtype given as a {type(value).__name__}")
    return value.build()


def _shape(value: object) -> tuple[int, ...]:
    if not isinstance(value, tuple) or len(value) > 32 or not all(isinstance(n, int) and 0 <= n for n in value):
        raise _Refused("an array shape")
    if int(np.prod(value, dtype=np.float64)) > MAX_ELEMENTS:
        raise _Refused(f"an array of more than {MAX_ELEMENTS} elements")
    return value


def _from_bytes(data: object, dtype: np.dtype, shape: tuple[int, ...], fortran: bool) -> np.ndarray:
    if isinstance(data, str):  # protocol-2 files hold bytes as latin-1 strings
        data = data.encode("latin1")
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise _Refused("an array's data")
    data = bytes(data)
    count = int(np.prod(shape))
    if len(data) != count * dtype.itemsize:
        raise _Refused("an array whose data does not match its shape")
    return np.frombuffer(data, dtype=dtype, count=count).reshape(shape, order="F" if fortran else "C").copy()


class _Array:
    """Stands for ``_reconstruct(ndarray, ...)`` and its ``BUILD``: the array is made from checked state."""

    def __init__(self, *args: object) -> None:
        self.array: np.ndarray | None = None

    def __setstate__(self, state: object) -> None:
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise _Refused("an array's state")
        _, shape, dtype, fortran, data = state if len(state) == 5 else (1, *state)
        shape, dtype = _shape(shape), _as_dtype(dtype)
        if dtype.hasobject:
            if not isinstance(data, list) or len(data) != int(np.prod(shape)):
                raise _Refused("an object array's items")
            array = np.empty(len(data), dtype=object)
            array[:] = data if data else array[:0]
            self.array = array.reshape(shape, order="F" if fortran else "C")
        else:
            self.array = _from_bytes(data, dtype, shape, bool(fortran))


def _reconstruct(cls: object, shape: object, typecode: object) -> _Array:
    if cls is not _NDARRAY:
        raise _Refused("an array of another class")
    return _Array()


def _scalar(dtype: object, data: object = b"") -> object:
    dtype = _as_dtype(dtype)
    if dtype.hasobject:
        return data
    return _from_bytes(data, dtype, (), False)[()]


def _frombuffer(buffer: object, dtype: object, shape: object, order: object) -> _Array:
    out = _Array()
    out.array = _from_bytes(buffer, _as_dtype(dtype), _shape(shape), order == "F")
    return out


class _Sparse:
    """Stands for a scipy sparse matrix of format ``fmt``: its state (the arrays) is checked and the matrix built
    from them."""

    fmt = ""

    def __init__(self, *args: object) -> None:
        self.state: dict | None = None

    def __setstate__(self, state: object) -> None:
        if not isinstance(state, dict):
            raise _Refused("a sparse matrix's state")
        self.state = state


_SPARSE_STANDINS = {name: type(f"_Sparse_{name}", (_Sparse,), {"fmt": name.split("_")[0]}) for name in _SPARSE}
_NDARRAY = object()  # what ``numpy.ndarray`` stands for: only ``_reconstruct`` takes it
_CODEC_NAMES = {"latin1", "latin-1", "iso-8859-1"}


def _encode(text: object, encoding: object = "utf-8") -> bytes:
    """``_codecs.encode`` as protocol-2 pickles use it for bytes: latin-1 text to bytes, nothing else."""
    if not isinstance(text, str) or encoding not in _CODEC_NAMES:
        raise _Refused("a codec other than latin-1")
    return text.encode("latin1")


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that only builds arrays, sparse matrices, containers, strings and numbers.

    Every numpy or scipy name a pickle may ask for resolves to a stand-in of this module that checks the state it
    is given (plain dtypes, shapes that match their data, bounded sizes) and builds the value itself; anything
    else is refused. :meth:`load` then turns the stand-ins into arrays and matrices, counting every value of the
    result as a tree (a list shared a thousand times counts a thousand times) against ``MAX_ITEMS`` and every array
    element against ``MAX_ELEMENTS``."""

    def __init__(self, file, path: Path, error: type[ElicitError] = UnsafeFileError) -> None:
        super().__init__(file, encoding="latin1")
        self.path, self.error = path, error

    def find_class(self, module: str, name: str) -> Any:
        key = (module, name)
        if key in _RECONSTRUCT:
            return _reconstruct
        if key in _SCALAR:
            return _scalar
        if key in _FROMBUFFER:
            return _frombuffer
        if key == ("numpy", "ndarray"):
            return _NDARRAY
        if key == ("numpy", "dtype"):
            return _Dtype
        if key == ("_codecs", "encode"):
            return _encode
        if module.split(".")[:2] == ["scipy", "sparse"] and name in _SPARSE:
            return _SPARSE_STANDINS[name]
        raise self.error(
            f"{self.path}: refused: it asks to run {module}.{name} while loading (only arrays, numbers, "
            "strings, lists and dicts are read from pickled files)"
        )

    def load(self) -> Any:
        value = super().load()
        return _Finisher(self.path, self.error).finish(value, 0)


class _Finisher:
    """Turns the stand-ins of a loaded pickle into arrays and matrices, within ``MAX_ITEMS``, ``MAX_ELEMENTS`` and
    ``MAX_DEPTH``."""

    def __init__(self, path: Path, error: type[ElicitError]) -> None:
        self.path, self.error, self.items, self.elements = path, error, 0, 0

    def _spend(self, items: int = 1, elements: int = 0) -> None:
        self.items += items
        self.elements += elements
        if self.items > MAX_ITEMS or self.elements > MAX_ELEMENTS:
            raise self.error(
                f"{self.path}: refused: it unfolds to more than {MAX_ITEMS} values or {MAX_ELEMENTS} array elements"
            )

    def finish(self, value: Any, depth: int) -> Any:
        if depth > MAX_DEPTH:
            raise self.error(f"{self.path}: refused: containers nested more than {MAX_DEPTH} deep")
        self._spend(1)
        if isinstance(value, _Array):
            if value.array is None:
                raise self.error(f"{self.path}: not a readable pickle (an array without its data)")
            array = value.array
            self._spend(elements=array.size)
            if array.dtype.hasobject:
                flat = [self.finish(v, depth + 1) for v in array.ravel()]
                array = np.empty(len(flat), dtype=object)
                array[:] = flat if flat else array[:0]
                return array.reshape(value.array.shape)
            return array
        if isinstance(value, _Sparse):
            return self._sparse(value, depth)
        if isinstance(value, _Dtype):
            return value.build()
        if isinstance(value, dict):
            return {self.finish(k, depth + 1): self.finish(v, depth + 1) for k, v in value.items()}
        if isinstance(value, list):
            return [self.finish(v, depth + 1) for v in value]
        if isinstance(value, tuple):
            return tuple(self.finish(v, depth + 1) for v in value)
        if isinstance(value, (str, bytes, int, float, complex, bool, type(None), np.generic)):
            return value
        raise self.error(f"{self.path}: refused: it holds a {type(value).__name__}")

    def _sparse(self, value: _Sparse, depth: int) -> Any:
        import scipy.sparse as sp

        state = value.state if isinstance(value.state, dict) else {}
        fields = {k: self.finish(state.get(k), depth + 1) for k in ("data", "indices", "indptr", "row", "col")}
        shape = state.get("_shape", state.get("shape"))
        fmt = value.fmt
        try:
            shape = _shape(tuple(int(n) for n in shape))
            if fmt in ("csc", "csr"):
                build = sp.csc_matrix if fmt == "csc" else sp.csr_matrix
                return build((fields["data"], fields["indices"], fields["indptr"]), shape=shape)
            if fmt == "coo":
                return sp.coo_matrix((fields["data"], (fields["row"], fields["col"])), shape=shape)
        except (TypeError, ValueError, _Refused) as exc:
            raise self.error(f"{self.path}: not a readable pickle (a sparse matrix: {exc})") from None
        raise self.error(f"{self.path}: not a readable pickle (a sparse matrix of format {fmt!r})")


PICKLE_ERRORS = (
    OSError, EOFError, pickle.UnpicklingError, ValueError, TypeError, AttributeError, IndexError, KeyError,
    RecursionError, MemoryError, OverflowError,
)  # fmt: skip


def load_pickle(path: str | Path, error: type[ElicitError] = UnsafeFileError) -> Any:
    """A pickled file (for example an SMPL ``.pkl``) through :class:`RestrictedUnpickler`; every problem
    is an ``error`` naming the file."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return RestrictedUnpickler(f, path, error).load()
    except ElicitError:
        raise
    except _Refused as exc:
        raise error(f"{path}: refused: {exc}") from None
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
    except ElicitError:
        raise
    except _Refused as exc:
        raise error(f"{path}: refused: {exc}") from None
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
