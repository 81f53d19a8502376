"""Leaf copies of small regions of big parameters, whose gradients are added back after the backward pass."""

from __future__ import annotations

from collections.abc import Callable

import torch


class GradRegions:
    """Regularisers that read a small region of a big grid (a random block, the unseen colour cells) read a leaf
    copy of it: autograd then builds a gradient the size of the region, and :meth:`add_gradients` adds it into
    the parameter's ``.grad``. Reading the parameter itself would build, zero and add a gradient the size of the
    whole grid for every read (most of a step's regulariser time on a 450k-cell grid)."""

    def __init__(self) -> None:
        self._taken: list[tuple[torch.Tensor, torch.Tensor, Callable[[torch.Tensor, torch.Tensor], None]]] = []

    def block(self, param: torch.Tensor, block: tuple[slice, ...]) -> torch.Tensor:
        """``param[block]`` (a box of slices) as a leaf."""
        leaf = param.detach()[block].clone().requires_grad_(param.requires_grad)
        self._taken.append((param, leaf, lambda grad, g: grad[block].add_(g)))
        return leaf

    def rows(self, param: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """Rows ``index`` of ``param`` seen as (-1, C) rows (C its last dimension) as a leaf (N, C)."""
        c = param.shape[-1]
        leaf = torch.index_select(param.detach().reshape(-1, c), 0, index).requires_grad_(param.requires_grad)
        self._taken.append((param, leaf, lambda grad, g: grad.view(-1, c).index_add_(0, index, g)))
        return leaf

    def add_gradients(self) -> None:
        """Add every region's gradient into its parameter's ``.grad`` (after ``backward``), then forget them."""
        for param, leaf, add in self._taken:
            if leaf.grad is not None:
                if param.grad is None:
                    param.grad = torch.zeros_like(param)
                add(param.grad, leaf.grad)
        self._taken.clear()
