"""The run folder's checkpoint: what a killed fit needs to continue, in a file that cannot carry code.

One safetensors file: the avatar's and the optimiser's tensors and the random streams' torch states
as tensors, everything else (step, stage, learning-rate scale, numpy stream states, statistics) as
JSON in its header, under ``format``.
"""

from __future__ import annotations

from pathlib import Path

import torch

from ..core.errors import ElicitError
from ..core.io import read_tensors, write_tensors

FORMAT = "elicit-checkpoint/2"
CHECKPOINT = "checkpoint.safetensors"


class FitError(ElicitError):
    """A fit that cannot start or continue."""


def optimizer_state(opt: torch.optim.Optimizer) -> dict:
    """The optimiser's state dict with string keys (JSON's), tensors kept."""
    sd = opt.state_dict()
    return {"state": {str(k): v for k, v in sd["state"].items()}, "param_groups": sd["param_groups"]}


def load_optimizer_state(opt: torch.optim.Optimizer, state: dict) -> None:
    """Inverse of :func:`optimizer_state`; raises ``ValueError`` when the parameter groups differ."""
    groups = state["param_groups"]
    if [len(g["params"]) for g in groups] != [len(g["params"]) for g in opt.param_groups]:
        raise ValueError("its optimiser has other parameter groups than this version's")
    opt.load_state_dict({"state": {int(k): v for k, v in state["state"].items()}, "param_groups": groups})


def save_checkpoint(run_dir: Path, state: dict) -> Path:
    return write_tensors(run_dir / CHECKPOINT, {"format": FORMAT, **state})


def read_checkpoint(run_dir: Path) -> dict:
    """The checkpoint of ``run_dir``; a damaged or foreign file is a :class:`FitError` naming it."""
    path = run_dir / CHECKPOINT
    try:
        state = read_tensors(path)
    except ValueError as exc:
        raise FitError(
            f"{path}: cannot resume from this checkpoint ({exc}); delete it, or fit without --resume"
        ) from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        found = state.get("format") if isinstance(state, dict) else None
        raise FitError(f"{path}: not an {FORMAT} checkpoint (format: {found!r}); delete it, or fit without --resume")
    return state
