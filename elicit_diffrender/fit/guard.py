"""Catches an avatar that emptied (or went NaN) and hands back its last good state.

HumanNeRF's known failure: with a bad step the density collapses and renders come out empty. The
guard measures the input coverage (mean rendered opacity inside the input mask, at low resolution);
an avatar counts as emptied when its coverage falls below ``MIN_COVERAGE`` *and* below half of the
last good state's, so one that starts empty (as without the body prior) may grow.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..model.avatar import Avatar
from .render import PoseRenderer
from .views import InputView

MIN_COVERAGE = 0.2
COVERAGE_SIZE = 96  # longer side of the coverage render, pixels


class EmptyRenderGuard:
    def __init__(self, avatar: Avatar, renderer: PoseRenderer, input_view: InputView) -> None:
        self.avatar, self.renderer, self.input = avatar, renderer, input_view
        self.good: dict[str, torch.Tensor] = {}
        self.good_coverage = 0.0

    @torch.no_grad()
    def coverage(self) -> float:
        """Mean rendered opacity inside the input mask (an empty mask counts as fully covered)."""
        cam = self.input.camera
        cam = cam.scaled(COVERAGE_SIZE / max(cam.width, cam.height))
        black = torch.zeros(3, device=self.avatar.device)
        alpha = self.renderer.render(cam, self.renderer.input_pose, black, ("alpha",), grad=False)["alpha"][0]
        mask = F.interpolate(self.input.mask[None, None], size=alpha.shape, mode="area")[0, 0] > 0.5
        return float(alpha[mask].mean()) if mask.any() else 1.0

    def remember(self, coverage: float | None = None) -> None:
        """Keep a copy of the avatar as the last good state, with its coverage."""
        self.good_coverage = self.coverage() if coverage is None else coverage
        self.good = {k: v.detach().clone() for k, v in self.avatar.state_dict().items()}

    def check(self) -> dict | None:
        """Remember the avatar if it is healthy; else restore the last good state and describe the event."""
        coverage = self.coverage()
        tensors = self.avatar.state_dict().values()
        finite = all(torch.isfinite(v).all() for v in tensors if v.is_floating_point())
        if finite and coverage >= min(MIN_COVERAGE, 0.5 * self.good_coverage):
            self.remember(coverage)
            return None
        self.avatar.load_state_dict(self.good)
        return {"coverage": coverage, "finite": finite}
