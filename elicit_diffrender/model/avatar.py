"""The animatable avatar: a canonical radiance grid warped to any pose by inverse LBS.

Rendering a (pose, camera): the body model gives the reduced skeleton's bone transforms for the pose;
the canonical occupancy grid, forward-warped with the motion weights, bounds and fills an
observation-space occupancy grid; rays are sampled only inside it, warped to canonical space by
the Warp skinning kernel (during a fit, by one look-up in the pose's baked warp), and composited by
the Warp ray marcher.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..body import BodyModel, load_body
from ..body.template import vertex_normals
from ..core.cameras import Camera
from ..core.errors import ElicitError
from ..core.geometry import axis_angle_to_matrix, rigid_inverse
from ..core.io import write_tensors
from .field import CanonicalField, MotionWeights, Room, grid_points, grid_shape, signed_distance
from .skinning import inverse_lbs
from .volume import BakedWarp, composite, sample_rays

FORMAT = "elicit-avatar/2"  # a safetensors file: the tensors, and the rest as JSON in its header
AVATAR_FILE = "avatar.safetensors"  # in a run folder
LEGACY_FORMAT = "elicit-avatar/1"  # avatar.pt from earlier versions, read with torch.load(weights_only=True)
LEGACY_FILE = "avatar.pt"
# Tensor names of elicit-avatar/1 files: renamed, or (None) no longer stored.
LEGACY_TENSORS = {"canonical_frames": "canonical_bones", "clothing_room": None}
FIELDS = ("body", "reduced_joints", "parents", "config", "voxel_size", "activation", "occupancy_cell", "weight_res")
BOUNDS_CELL = 0.04  # metres: lattice that bounds the posed body when occupancy skipping is off


class AvatarError(ElicitError):
    """An avatar file that cannot be read."""


def room_box(vertices: np.ndarray, normals: np.ndarray, room: Room, cell: float = BOUNDS_CELL) -> np.ndarray:
    """(2, 3) the box around the canonical body and its ``room``: the body's box with ``room.margin`` on every side,
    grown to the lattice points (``cell`` apart) within their room of the body."""
    lo, hi = vertices.min(0) - room.margin, vertices.max(0) + room.margin
    if room.widest > room.margin:
        wide = np.stack([vertices.min(0) - room.widest, vertices.max(0) + room.widest])
        pts = grid_points(torch.as_tensor(wide), grid_shape(torch.as_tensor(wide), cell)).reshape(-1, 3).numpy()
        pts = pts[signed_distance(pts, vertices, normals) < room(pts)]
        lo, hi = np.minimum(lo, pts.min(0) - cell), np.maximum(hi, pts.max(0) + cell)
    return np.stack([lo, hi])


def sample_grid(volume: torch.Tensor, box: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Trilinear look-up of a (C, X, Y, Z) node-aligned volume at (N, 3) points -> (N, C)."""
    norm = 2 * (points - box[0]) / (box[1] - box[0]) - 1
    out = F.grid_sample(
        volume[None],
        norm.flip(-1).reshape(1, 1, 1, -1, 3).to(volume.dtype),
        mode="bilinear",
        padding_mode="border",
        align_corners=True,
    )
    return out.reshape(volume.shape[0], -1).T


@dataclass
class CanonicalLookup:
    """A host copy of the avatar's canonical grids, looked up as the renderer looks them up: the raw density
    trilinearly, then activated; the foreground from the bones' summed weights (one channel: a trilinear
    look-up is linear); the colour logits, then the sigmoid. Made by :meth:`Avatar.canonical_lookup`."""

    box: torch.Tensor
    raw_density: torch.Tensor  # (1, X, Y, Z)
    color_logits: torch.Tensor  # (3, X, Y, Z)
    summed_weights: torch.Tensor  # (1, X', Y', Z')
    weights_box: torch.Tensor
    activate: Callable[[torch.Tensor], torch.Tensor]
    foreground: Callable[[torch.Tensor], torch.Tensor]

    def density(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N,) density ``sigma`` and (N,) foreground likelihood ``fg`` at (N, 3) canonical points."""
        sigma = self.activate(sample_grid(self.raw_density, self.box, points)[:, 0])
        return sigma, self.foreground(sample_grid(self.summed_weights, self.weights_box, points)[:, 0])

    def srgb(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) sRGB colour in [0, 1] at (N, 3) canonical points."""
        return torch.sigmoid(sample_grid(self.color_logits, self.box, points))


class Avatar(nn.Module):
    def __init__(
        self,
        body_spec: dict,
        reduced_joints: list[str],
        parents: list[int],
        canonical_bones: torch.Tensor,
        box: torch.Tensor,
        voxel_size: float,
        activation: str,
        occupancy_cell: float,
        weight_res: int,
        config: dict | None = None,
    ) -> None:
        super().__init__()
        self.body_spec = dict(body_spec)
        self.reduced_joints = list(reduced_joints)
        self.parents = list(parents)
        self.config = dict(config or {})
        self.register_buffer("canonical_bones", canonical_bones.to(torch.float32).clone())
        self.field = CanonicalField(box, voxel_size, activation, occupancy_cell)
        self.motion_weights = MotionWeights(box, len(reduced_joints), weight_res)
        # A rotation per reduced joint for each refined pose (the fit's input poses), (K, B, 3)
        self.pose_delta = nn.Parameter(torch.zeros(1, len(reduced_joints), 3))
        # The body-model poses (pose, orient, transl, flattened) that ``pose_delta`` corrects, (K, D); empty: none
        self.register_buffer("refined_pose", torch.zeros(0, dtype=torch.float64))
        self._body: BodyModel | None = None
        # The canonical body's signed distance at the field's nodes (``from_body``; not stored in files)
        self.body_sdf: np.ndarray | None = None

    # ---- construction ------------------------------------------------------------------------------
    @classmethod
    def from_body(
        cls,
        body: BodyModel,
        body_spec: dict,
        voxel_size: float = 0.016,
        room: Room | float = 0.10,
        activation: str = "softplus",
        occupancy_cell: float = 0.04,
        weight_res: int = 32,
        config: dict | None = None,
        body_prior: bool = True,
    ) -> Avatar:
        """An avatar in ``body``'s canonical pose, its motion weights splatted from the body's skinning.

        ``room`` (a :class:`Room`, or one margin in metres) is how far outside the body the avatar may hold
        density; the box bounds it. With ``body_prior`` the density starts as the canonical body and
        empty-space skipping is limited to the room; without (the no-initialisation ablation) the grid
        starts empty and every cell of the box may be filled.
        """
        room = room if isinstance(room, Room) else Room(float(room))
        canon = body.pose(body.canonical_pose())
        verts = canon.vertices
        normals = vertex_normals(verts, body.faces)
        box = torch.tensor(room_box(verts, normals, room), dtype=torch.float32)
        keep = [body.joint_index(n) for n in body.reduced_joints]
        mapping = body.reduced_map()
        parents = [-1 if body.parents[j] < 0 else int(mapping[body.parents[j]]) for j in keep]
        avatar = cls(
            body_spec,
            body.reduced_joints,
            parents,
            torch.as_tensor(canon.bone_transforms[keep]),
            box,
            voxel_size,
            activation,
            occupancy_cell,
            weight_res,
            config,
        )
        avatar.motion_weights.init_from_body(verts, normals, body.reduced_weights(), room, avatar.room_weight)
        avatar.body_sdf = avatar.field.body_distance(verts, normals)
        if body_prior:
            avatar.field.init_from_body(avatar.body_sdf, verts, normals, room=room)
        avatar._body = body
        return avatar

    @property
    def sharpness(self) -> int:
        """The inverse warp's blend exponent (``warp_sharpness``; avatars from before it existed used 1)."""
        return int(self.config.get("warp_sharpness", 1))

    @property
    def gate(self) -> float:
        """The inverse warp's gate in metres (``warp_gate``; avatars from before it existed used none)."""
        return float(self.config.get("warp_gate", 0.0))

    @property
    def room_weight(self) -> float:
        """The room's share of the motion weights (``room_weight``; avatars from before it existed used 1)."""
        return float(self.config.get("room_weight", 1.0))

    def foreground(self, summed_weights: torch.Tensor) -> torch.Tensor:
        """The foreground likelihood of points whose bone weights sum to ``summed_weights``: the room's share
        scaled back to 1, and clamped there (bones whose candidates both carry weight must not add up past 1)."""
        return (summed_weights / self.room_weight).clamp(max=1.0)

    @torch.no_grad()
    def canonical_lookup(self) -> CanonicalLookup:
        """The canonical grids on the host, for look-ups outside the renderer (mesh, texture)."""
        f = self.field
        return CanonicalLookup(
            box=f.box.detach().cpu(),
            raw_density=f.density.detach()[None].cpu(),
            color_logits=f.color.detach().permute(3, 0, 1, 2).cpu(),
            summed_weights=self.motion_weights().detach().cpu().sum(0, keepdim=True),
            weights_box=self.motion_weights.box.cpu(),
            activate=f.activate,
            foreground=self.foreground,
        )

    @property
    def device(self) -> torch.device:
        return self.field.density.device

    @property
    def body(self) -> BodyModel:
        if self._body is None:
            self._body = load_body(self.body_spec)
        return self._body

    # ---- poses: a pose is the (B, 4, 4) world transforms of the reduced skeleton's bones ------------------
    def bone_transforms(
        self, pose: np.ndarray, global_orient: np.ndarray, transl: np.ndarray, refine: bool = True
    ) -> torch.Tensor:
        """(B, 4, 4) world transforms of the reduced skeleton for one pose of the body model; the input pose
        carries its learned correction (``refine_input_pose``) unless ``refine`` is off."""
        posed = self.body.pose(pose, global_orient, transl)
        bones = torch.as_tensor(self.body.reduced_transforms(posed), dtype=torch.float32, device=self.device)
        k = self.refined_index(pose, global_orient, transl) if refine else None
        return bones if k is None else self.refined(bones, k)

    @staticmethod
    def _flat_pose(pose: np.ndarray, global_orient: np.ndarray, transl: np.ndarray) -> np.ndarray:
        return np.concatenate([np.ravel(pose), np.ravel(global_orient), np.ravel(transl)]).astype(np.float64)

    def set_refined_poses(self, poses: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None:
        """Name the body-model poses (pose, orient, transl) that ``pose_delta`` corrects (the fit's input poses);
        their corrections start at zero."""
        flat = np.stack([self._flat_pose(*p) for p in poses])
        self.refined_pose = torch.as_tensor(flat, device=self.device)
        shape = (len(poses), len(self.reduced_joints), 3)
        self.pose_delta = nn.Parameter(torch.zeros(shape, device=self.device), self.pose_delta.requires_grad)

    def refined_index(self, pose: np.ndarray, global_orient: np.ndarray, transl: np.ndarray) -> int | None:
        """Which of the refined poses this body-model pose is (``bone_transforms`` corrects it); None: none."""
        flat = self._flat_pose(pose, global_orient, transl)
        ref = self.refined_pose.detach().cpu().numpy().reshape(-1, flat.size) if self.refined_pose.numel() else []
        for k, row in enumerate(ref):
            if np.allclose(row, flat, rtol=0.0, atol=1e-6):
                return k
        return None

    def refined(self, bones: torch.Tensor, k: int = 0) -> torch.Tensor:
        """Apply refined pose ``k``'s learned correction (a rotation per reduced joint, down the kinematic chain)."""
        local = []
        for b, p in enumerate(self.parents):
            local.append(bones[b] if p < 0 else rigid_inverse(bones[p]) @ bones[b])
        delta = torch.eye(4, device=bones.device).repeat(len(self.parents), 1, 1)
        delta[:, :3, :3] = axis_angle_to_matrix(self.pose_delta[k])
        out: list[torch.Tensor] = []
        for b, p in enumerate(self.parents):
            out.append((local[b] if p < 0 else out[p] @ local[b]) @ delta[b])
        return torch.stack(out)

    def obs_to_canonical(self, bones: torch.Tensor) -> torch.Tensor:
        return self.canonical_bones @ rigid_inverse(bones)

    # ---- rendering ----------------------------------------------------------------------------------
    @property
    def bounds_cell(self) -> float:
        """Metres between the cells whose samples bound a pose's observation space: the occupancy grid's, or
        ``BOUNDS_CELL`` without empty-space skipping."""
        return self.field.occupancy_cell if self.field.occupancy_cell > 0 else BOUNDS_CELL

    @torch.no_grad()
    def skinning_samples(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The canonical points that bound every pose's observation space and their normalised bone weights,
        ((N, 3), (N, B)): eight points about the centre of every occupied cell (every cell of a ``BOUNDS_CELL``
        lattice over the box without skipping). They depend on the grid and the motion weights, not on the pose:
        one set serves every pose's :meth:`observation_space`."""
        f = self.field
        dev = self.device
        skipping, cell = f.occupancy_cell > 0, self.bounds_cell
        shape = tuple(f.occupancy.shape) if skipping else grid_shape(f.box.cpu(), cell)
        cells = torch.as_tensor(grid_points(f.box.double().cpu(), shape), dtype=torch.float32, device=dev)
        occupied = cells[f.occupancy.bool()] if skipping else cells.reshape(-1, 3)
        if occupied.shape[0] == 0:
            occupied = cells.reshape(-1, 3)
        step = max(cell, f.voxel_size) / 4.0
        offsets = torch.tensor(
            [[x, y, z] for x in (-step, step) for y in (-step, step) for z in (-step, step)], device=dev
        )
        pts = (occupied[:, None] + offsets[None]).reshape(-1, 3)
        w = sample_grid(self.motion_weights(), self.motion_weights.box, pts)  # (N, B)
        return pts, w / w.sum(1, keepdim=True).clamp(min=1e-6)

    @torch.no_grad()
    def observation_space(
        self, bones: torch.Tensor, margin: float = 0.03, samples: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The observation-space box and occupancy grid for a pose, from the forward-warped canonical cells
        (``samples``: :meth:`skinning_samples`, computed here when not given)."""
        f = self.field
        dev = self.device
        pts, w = samples if samples is not None else self.skinning_samples()
        can_to_obs = bones @ rigid_inverse(self.canonical_bones)
        posed = torch.einsum("nb,bij,nj->ni", w, can_to_obs[:, :3, :3], pts) + w @ can_to_obs[:, :3, 3]
        pad = margin + max(self.bounds_cell, f.voxel_size)
        box = torch.stack([posed.min(0).values - pad, posed.max(0).values + pad])
        host = box.cpu()  # renders read the box on the host (kernel arguments)
        if f.occupancy_cell <= 0:  # no empty-space skipping: no occupancy grid
            return host, None
        shape = tuple(max(2, int(np.ceil(float(e) / f.occupancy_cell))) for e in (host[1] - host[0]))
        size = torch.tensor(shape, device=dev)
        idx = ((posed - box[0]) / (box[1] - box[0]) * size).long()
        idx = torch.minimum(idx.clamp(min=0), size - 1)
        occ = torch.zeros(shape, device=dev)
        occ[idx[:, 0], idx[:, 1], idx[:, 2]] = 1.0
        occ = F.max_pool3d(occ[None, None], 3, 1, 1)[0, 0]
        return host, occ.to(torch.uint8)

    @torch.no_grad()
    def bake_warp(self, bones: torch.Tensor, box: torch.Tensor, cell: float, chunk: int = 1 << 18) -> torch.Tensor:
        """The inverse warp of a pose as a look-up table: (X, Y, Z, 4) summed bone weight ``fg`` times canonical
        position, and ``fg``, at the nodes of a lattice ``cell`` metres apart over the observation-space ``box``.

        Trilinear look-ups in it (:class:`BakedWarp` in :meth:`render_rays`, ``skinning.lookup_baked_warp``)
        replace the per-bone warp of every sample while the motion weights and the pose are fixed. The position is
        weighted by ``fg`` so that nodes outside every bone's reach (``fg = 0``, position meaningless) do not pull a
        look-up beside them; between nodes where the warp jumps (a gate between two limbs) a look-up blends the two
        sides.
        """
        shape = grid_shape(box.cpu(), cell)
        nodes = grid_points(box.double().cpu(), shape).reshape(-1, 3).to(torch.float32).to(self.device)
        out = []
        for s in range(0, nodes.shape[0], chunk):
            x_c, fg = self._exact_warp(nodes[s : s + chunk], bones)
            out.append(torch.cat([x_c * fg[:, None], fg[:, None]], 1))
        return torch.cat(out).reshape(*shape, 4)

    def _exact_warp(self, points: torch.Tensor, bones: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The per-bone inverse warp: canonical points and the summed bone weights (before :meth:`foreground`)."""
        weights = self.motion_weights() if self.motion_weights.logits.requires_grad else self.motion_weights().detach()
        return inverse_lbs(
            points, self.obs_to_canonical(bones), weights, self.motion_weights.box_host, sharpness=self.sharpness,
            gate=self.gate,
        )  # fmt: skip

    def warp_points(self, points: torch.Tensor, bones: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Observation-space points (N, 3) -> canonical points (N, 3) and foreground likelihood (N,) by the exact
        inverse warp."""
        x_c, fg = self._exact_warp(points, bones)
        return x_c, self.foreground(fg)

    def render_rays(
        self,
        origins: torch.Tensor,
        dirs: torch.Tensor,
        bones: torch.Tensor,
        n_samples: int,
        background: torch.Tensor | None = None,
        jitter: bool = False,
        seed: int = 0,
        outputs: tuple[str, ...] = ("rgb", "alpha"),
        t_thresh: float = 1e-3,
        space: tuple[torch.Tensor, torch.Tensor | None] | None = None,
        warp: BakedWarp | None = None,
    ) -> dict[str, torch.Tensor]:
        """Render rays in the pose ``bones`` (B, 4, 4); colour is composited over ``background``. ``warp``: the
        pose's warp as a look-up table (:meth:`bake_warp`) that the ray sampler applies, instead of the exact
        warp of every sample."""
        box, occ = space if space is not None else self.observation_space(bones.detach())
        samples = sample_rays(origins, dirs, box, n_samples, jitter=jitter, seed=seed, occupancy=occ, warp=warp)
        if warp is not None:
            x_c, fg = samples.positions, self.foreground(samples.fg)
        else:
            x_c, fg = self.warp_points(samples.positions, bones)
        f = self.field
        out = composite(
            samples,
            f.density,
            f.color if "rgb" in outputs else None,
            f.box_host,
            positions=x_c,
            fg=fg,
            outputs=outputs,
            activation=f.activation,
            t_thresh=t_thresh,
            density_scale=1.0 / f.voxel_size,
        )
        if "rgb" in out and background is not None:
            out["rgb"] = out["rgb"] + (1.0 - out["alpha"])[:, None] * background
        return out

    @torch.no_grad()
    def render_image(
        self,
        camera: Camera,
        bones: torch.Tensor,
        n_samples: int = 64,
        background=(0.0, 0.0, 0.0),
        chunk: int = 32768,
        t_thresh: float = 1e-3,
    ) -> dict[str, np.ndarray]:
        """A full image: (H, W, 3) colour and (H, W) alpha."""
        space = self.observation_space(bones)
        origins, dirs = camera.rays(device=self.device)
        bg = torch.tensor(background, dtype=torch.float32, device=self.device)
        rgb, alpha = [], []
        for s in range(0, origins.shape[0], chunk):
            out = self.render_rays(
                origins[s : s + chunk], dirs[s : s + chunk], bones, n_samples, bg, space=space, t_thresh=t_thresh
            )
            rgb.append(out["rgb"])
            alpha.append(out["alpha"])
        h, w = camera.height, camera.width
        return {
            "rgb": torch.cat(rgb).reshape(h, w, 3).cpu().numpy(),
            "alpha": torch.cat(alpha).reshape(h, w).cpu().numpy(),
        }

    def render_pose(
        self, camera: Camera, pose: np.ndarray, orient: np.ndarray, transl: np.ndarray, n_samples: int = 64
    ) -> dict[str, np.ndarray]:
        """A full image of the avatar in a body-model pose (the interface shared with the baselines)."""
        return self.render_image(camera, self.bone_transforms(pose, orient, transl), n_samples)

    # ---- files ------------------------------------------------------------------------------------------
    def state(self) -> dict:
        return {
            "format": FORMAT,
            "body": self.body_spec,
            "reduced_joints": self.reduced_joints,
            "parents": self.parents,
            "config": self.config,
            "voxel_size": self.field.voxel_size,
            "activation": self.field.activation,
            "occupancy_cell": self.field.occupancy_cell,
            "weight_res": int(self.motion_weights.logits.shape[1]),
            "tensors": {k: v.detach().cpu() for k, v in self.state_dict().items()},
        }

    def save(self, path: str | Path) -> Path:
        return write_tensors(path, self.state())

    @classmethod
    def from_state(cls, data: dict) -> Avatar:
        """The avatar of an ``elicit-avatar/2`` (or ``/1``) state; a bad one is an :class:`AvatarError`."""
        found = data.get("format") if isinstance(data, dict) else None
        if found not in (FORMAT, LEGACY_FORMAT):
            raise AvatarError(f"not an {FORMAT} avatar (format: {found!r})")
        missing = [k for k in (*FIELDS, "tensors") if k not in data]
        if missing:
            raise AvatarError(f"an {found} avatar without the field(s) {missing}")
        renamed = {k: LEGACY_TENSORS.get(k, k) for k in data["tensors"]}
        t = {new: data["tensors"][old] for old, new in renamed.items() if new is not None}
        try:
            avatar = cls(
                data["body"],
                data["reduced_joints"],
                data["parents"],
                t["canonical_bones"],
                t["field.box"],
                data["voxel_size"],
                data["activation"],
                data["occupancy_cell"],
                data["weight_res"],
                data["config"],
            )
            refined = t.setdefault("refined_pose", torch.zeros(0, dtype=torch.float64)).clone()
            if t["pose_delta"].dim() == 2:  # files from before multi-photo fits: one refined pose
                t["pose_delta"] = t["pose_delta"][None]
                refined = refined.reshape(1, -1) if refined.numel() else refined
            t["refined_pose"] = refined
            avatar.refined_pose = refined
            avatar.pose_delta = nn.Parameter(torch.zeros_like(t["pose_delta"]))
            avatar.load_state_dict(t)
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            detail = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
            raise AvatarError(
                f"an {found} avatar whose fields do not fit together ({type(exc).__name__}: {detail})"
            ) from None
        return avatar
