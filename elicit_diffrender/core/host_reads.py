"""Reads that bring a tensor's value to the host, each of which waits for the device (a host sync), counted.

A training step should make none outside its periodic read-outs (the loss log, the guard, previews, checkpoints)
but the ray sampler's sample count, whose value sizes the step's buffers. On CUDA,
``torch.cuda.set_sync_debug_mode`` finds them; on the CPU nothing waits, so :func:`count_host_reads` counts the
calls that would: ``item``, ``float``/``int``/``bool`` of a tensor (a Python branch on a tensor value included),
``tolist``, ``numpy``, ``cpu``, ``nonzero`` and indexing with a bool tensor. Host-side tensors by design (a CPU
generator's draws, crops of host images, boxes kept on the host) are read inside :func:`on_host`, which the
counter skips for CPU tensors only, so that on CUDA a device tensor read there still counts.
"""

from __future__ import annotations

import contextlib
import threading
import traceback
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

import torch

_state = threading.local()
_PACKAGE = "elicit_diffrender"
_METHODS = ("item", "tolist", "numpy", "cpu", "nonzero", "__bool__", "__float__", "__int__", "__index__")


@contextlib.contextmanager
def on_host() -> Iterator[None]:
    """Reads of CPU tensors inside are host work by design, not host syncs."""
    depth = getattr(_state, "host", 0)
    _state.host = depth + 1
    try:
        yield
    finally:
        _state.host = depth


@dataclass
class HostReads:
    """The reads seen: ``sites`` counts each (kind, ``file:line`` of the first frame in the package)."""

    sites: Counter = field(default_factory=Counter)

    @property
    def total(self) -> int:
        return sum(self.sites.values())

    def take(self) -> Counter:
        """The reads since the last ``take``, and forget them."""
        out, self.sites = self.sites, Counter()
        return out


def _site() -> str:
    for frame in reversed(traceback.extract_stack()[:-2]):
        if f"/{_PACKAGE}/" in frame.filename and not frame.filename.endswith("host_reads.py"):
            return f"{frame.filename.split(f'/{_PACKAGE}/')[-1]}:{frame.lineno}"
    return "outside the package"


def _counted(reads: HostReads, kind: str, original):
    def wrapper(tensor, *args, **kwargs):
        if not (getattr(_state, "host", 0) and tensor.device.type == "cpu") and not getattr(_state, "inside", False):
            reads.sites[(kind, _site())] += 1
        _state.inside, outer = True, getattr(_state, "inside", False)
        try:
            return original(tensor, *args, **kwargs)
        finally:
            _state.inside = outer

    return wrapper


def _bool_index(index) -> bool:
    items = index if isinstance(index, tuple) else (index,)
    return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in items)


@contextlib.contextmanager
def count_host_reads() -> Iterator[HostReads]:
    """Count every host read of a tensor inside (see the module's docstring); not thread-safe, for tests and
    profiles."""
    reads = HostReads()
    saved = {name: getattr(torch.Tensor, name) for name in (*_METHODS, "__getitem__")}
    saved_nonzero = torch.nonzero
    for name in _METHODS:
        setattr(torch.Tensor, name, _counted(reads, name.strip("_"), saved[name]))
    getitem = _counted(reads, "bool index", saved["__getitem__"])
    torch.Tensor.__getitem__ = lambda t, i: getitem(t, i) if _bool_index(i) else saved["__getitem__"](t, i)
    nonzero = _counted(reads, "nonzero", saved_nonzero)
    torch.nonzero = lambda t, *a, **k: nonzero(t, *a, **k)
    try:
        yield reads
    finally:
        for name, method in saved.items():
            setattr(torch.Tensor, name, method)
        torch.nonzero = saved_nonzero
