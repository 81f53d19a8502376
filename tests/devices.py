"""The device the kernel tests launch on: ``ELICIT_DEVICE`` (``cpu`` by default, ``cuda`` on a GPU machine).

The tests build their inputs and check their results on the CPU; :func:`on_device` wraps a kernel entry point
so that its tensor arguments travel to the test device and its results come back. ``.to`` is differentiable, so
gradients still reach the tests' CPU leaves, and a GPU run compares the CUDA kernels against the CPU references.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Callable
from typing import Any

import torch

DEVICE = torch.device(os.environ.get("ELICIT_DEVICE") or "cpu")
CPU = torch.device("cpu")


def moved(value: Any, device: torch.device) -> Any:
    """``value`` with every tensor in it (also inside dataclasses, dicts, lists and tuples) on ``device``."""
    if isinstance(value, torch.Tensor):
        return value.to(device)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.replace(
            value, **{f.name: moved(getattr(value, f.name), device) for f in dataclasses.fields(value)}
        )
    if isinstance(value, dict):
        return {k: moved(v, device) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(moved(v, device) for v in value)
    return value


def on_device(fn: Callable) -> Callable:
    """``fn`` run on :data:`DEVICE`, taking and returning CPU tensors (``fn`` itself on the CPU)."""
    if DEVICE.type == "cpu":
        return fn

    @functools.wraps(fn)
    def run(*args, **kwargs):
        return moved(fn(*moved(args, DEVICE), **moved(kwargs, DEVICE)), CPU)

    return run
