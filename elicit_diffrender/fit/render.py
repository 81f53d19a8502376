"""Renders the avatar being fitted at the training poses: cached bone transforms and observation spaces."""

from __future__ import annotations

import numpy as np
import torch

from ..core.cameras import Camera
from ..data.subject import Subject
from ..model.avatar import Avatar
from ..model.volume import BakedWarp
from .streams import RandomStreams

SPACE_REFRESH = 50  # steps between observation-space updates while the warp itself is learned


class PoseRenderer:
    """Differentiable crops and full images of the avatar in the subject's motion poses.

    The observation-space box and occupancy of a pose are cached; when the motion weights (or the
    refined input pose) are being learned they are rebuilt every ``SPACE_REFRESH`` steps. The warp of a
    pose whose warp is fixed is baked into a look-up table of ``warp_cell`` metres once (0: every sample
    takes the exact per-bone warp), which the ray sampler applies. Training renders jitter their samples with
    seeds from ``streams.jitter``; renders without gradients draw nothing from any stream.
    """

    def __init__(
        self,
        avatar: Avatar,
        subject: Subject,
        poses: list[int],
        samples_per_ray: int,
        t_thresh: float,
        streams: RandomStreams,
        warp_cell: float = 0.0,
    ) -> None:
        self.avatar, self.streams, self.warp_cell = avatar, streams, warp_cell
        self.samples_per_ray, self.t_thresh = samples_per_ray, t_thresh
        self.input_pose = subject.input_index
        self._bones = {p: avatar.bone_transforms(*subject.motion.frame(p), refine=False) for p in poses}
        # The poses the avatar itself corrects when it renders them (``Avatar.set_refined_poses``): pose -> row
        refined = {p: avatar.refined_index(*subject.motion.frame(p)) for p in poses}
        self._refined = {p: k for p, k in refined.items() if k is not None}
        self._spaces: dict[int, tuple] = {}
        self._baked: dict[int, BakedWarp] = {}
        self._space_key = -1
        self.refresh(0)

    def bones(self, pose: int) -> torch.Tensor:
        """(B, 4, 4) bone transforms of a training pose, with the learned correction on the input pose."""
        bones = self._bones[pose]
        return self.avatar.refined(bones, self._refined[pose]) if pose in self._refined else bones

    def _moving(self, pose: int) -> bool:
        return self.avatar.motion_weights.logits.requires_grad or pose in self._refined

    def refresh(self, step: int) -> None:
        """Build the space (and baked warp) of every training pose not built yet, and rebuild those whose warp is
        learned, once every ``SPACE_REFRESH`` steps: all at once, so that the reads a build needs (the box, the
        occupied cells) fall on that step and on no other."""
        key = step // SPACE_REFRESH
        if key != self._space_key:
            self._space_key = key
            self._spaces = {p: s for p, s in self._spaces.items() if not self._moving(p)}
            missing = [p for p in self._bones if p not in self._spaces]
            samples = self.avatar.skinning_samples() if missing else None  # one set for every pose
            for pose in missing:
                self.space(pose, samples)
            for pose in self._bones:
                self.baked(pose)

    def invalidate(self) -> None:
        """Rebuild the learned poses' spaces at the next :meth:`refresh` (the avatar was loaded from a file)."""
        self._space_key = -1

    def space(self, pose: int, samples: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple:
        """The pose's observation space, built once (``samples``: ``Avatar.skinning_samples``, if at hand)."""
        if pose not in self._spaces:
            self._spaces[pose] = self.avatar.observation_space(self.bones(pose).detach(), samples=samples)
        return self._spaces[pose]

    def baked(self, pose: int) -> BakedWarp | None:
        """The pose's warp as a look-up table, while the warp is fixed and ``warp_cell`` > 0."""
        if self.warp_cell <= 0 or self._moving(pose):
            return None
        if pose not in self._baked:
            box = self.space(pose)[0]
            self._baked[pose] = BakedWarp(self.avatar.bake_warp(self.bones(pose).detach(), box, self.warp_cell), box)
        return self._baked[pose]

    def render(
        self, camera: Camera, pose: int, background: torch.Tensor, outputs=("rgb", "alpha"), grad: bool = True
    ) -> dict[str, torch.Tensor]:
        """Render ``camera``'s pixels: ``alpha`` (1, H, W) and, if asked, ``rgb`` (1, 3, H, W)."""
        origins, dirs = camera.rays(device=self.avatar.device)
        with torch.set_grad_enabled(grad):
            out = self.avatar.render_rays(
                origins,
                dirs,
                self.bones(pose),
                self.samples_per_ray,
                background,
                jitter=grad,
                seed=self.streams.jitter_seed() if grad else 0,
                outputs=outputs,
                t_thresh=self.t_thresh,
                space=self.space(pose),
                warp=self.baked(pose),
            )
        h, w = camera.height, camera.width
        res = {"alpha": out["alpha"].reshape(1, h, w)}
        if "rgb" in out:
            res["rgb"] = out["rgb"].reshape(h, w, 3).permute(2, 0, 1)[None]
        return res

    def image(self, camera: Camera, pose: int) -> np.ndarray:
        """A full (H, W, 3) image on black, without gradients (previews), from the cached space and baked warp."""
        black = torch.zeros(3, device=self.avatar.device)
        return self.render(camera, pose, black, grad=False)["rgb"][0].permute(1, 2, 0).cpu().numpy()
