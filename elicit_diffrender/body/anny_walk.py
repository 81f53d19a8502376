"""Anny's shipped walk cycle (MPFB2 ``walkcycles/crappy_experimental_female.json``) as a motion.

The clip is a set of Blender keyframes on MPFB's default rig: Euler rotations (and a root offset)
for the spine, neck, head and clavicles, and IK targets for the limbs: ``*_foot_ik``/``*_hand_ik``
(reach and rotation of the foot and hand) and ``*_knee_ik``/``*_elbow_ik`` (where the knee and elbow
point). The curves are evaluated as Blender's Bezier keyframes; the limbs are solved by a batched
two-bone IK over the whole clip (reach the target, bend toward the knee/elbow target, copy the
target's rotation), and the result is converted to Anny's ``local-ref`` rotations. Anny's rest bone
frames follow Blender's convention (y along the bone), so a keyframe means what it meant in Blender.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from .anny_model import ANNY_TO_WORLD, AnnyBody, import_anny

WALK_CYCLE_FILE = Path("mpfb2") / "walkcycles" / "crappy_experimental_female.json"
# MPFB's root bone runs from behind the pelvis to its front (Blender coordinates of the default rig):
# its frame, unlike Anny's world-aligned root, has y pointing forward.
MPFB_ROOT_HEAD, MPFB_ROOT_TAIL = (0.0, 0.06477, 0.05176), (0.0, -0.01320, 0.05598)
FK_BONES = ("root", "spine01", "spine02", "spine03", "spine04", "spine05", "neck01", "head", "clavicle.L", "clavicle.R")
# ((upper bone, its twin, lower bone, its twin, end bone), reach target, bend target)
LIMBS = [
    ((f"{u}01.{s}", f"{u}02.{s}", f"{lo}01.{s}", f"{lo}02.{s}", f"{end}.{s}"), f"{side}_{reach}_ik",
     f"{side}_{bend}_ik")
    for s, side in (("L", "left"), ("R", "right"))
    for u, lo, end, reach, bend in (("upperleg", "lowerleg", "foot", "foot", "knee"),
                                    ("upperarm", "lowerarm", "wrist", "hand", "elbow"))
]  # fmt: skip


def walk_cycle_path() -> Path:
    return Path(import_anny().__file__).parent / "data" / WALK_CYCLE_FILE


def _bezier(keys: list[tuple[float, float, list, list]], t: np.ndarray) -> np.ndarray:
    """Blender F-curve: cubic Bezier segments between keyframes, constant outside."""
    frames = np.array([k[0] for k in keys])
    out = np.empty_like(t)
    for i, ti in enumerate(t):
        if ti <= frames[0] or len(keys) == 1:
            out[i] = keys[0][1]
            continue
        if ti >= frames[-1]:
            out[i] = keys[-1][1]
            continue
        j = int(np.searchsorted(frames, ti, side="right")) - 1
        (f0, v0, _, r0), (f1, v1, l1, _) = keys[j], keys[j + 1]
        px = np.array([f0, r0[0], l1[0], f1])
        py = np.array([v0, r0[1], l1[1], v1])
        lo, hi = 0.0, 1.0  # x(s) is monotonic for Blender's clamped handles: bisect for x(s) = ti
        for _ in range(40):
            s = 0.5 * (lo + hi)
            x = (1 - s) ** 3 * px[0] + 3 * (1 - s) ** 2 * s * px[1] + 3 * (1 - s) * s**2 * px[2] + s**3 * px[3]
            lo, hi = (s, hi) if x < ti else (lo, s)
        s = 0.5 * (lo + hi)
        out[i] = (1 - s) ** 3 * py[0] + 3 * (1 - s) ** 2 * s * py[1] + 3 * (1 - s) * s**2 * py[2] + s**3 * py[3]
    return out


def _channel(data: dict, bone: str, name: str, t: np.ndarray) -> np.ndarray:
    """(n, 3) values of one channel (``rotation_euler`` or ``location``); zeros when not keyed."""
    keyed = sorted(((float(f), v[name]) for f, v in data.get(bone, {}).items() if name in v), key=lambda x: x[0])
    if not keyed:
        return np.zeros((t.shape[0], 3))
    cols = []
    for c in range(3):
        keys = [(f, ch["values"][c], ch["metadata"][c]["handle_left"], ch["metadata"][c]["handle_right"])
                for f, ch in keyed]  # fmt: skip
        cols.append(_bezier(keys, t))
    return np.stack(cols, axis=1)


def _euler_xyz(e: torch.Tensor) -> torch.Tensor:
    """Blender's XYZ Euler rotation, Rz @ Ry @ Rx, for (..., 3) angles."""
    c, s = torch.cos(e), torch.sin(e)
    one, zero = torch.ones_like(c[..., 0]), torch.zeros_like(c[..., 0])
    rx = torch.stack([one, zero, zero, zero, c[..., 0], -s[..., 0], zero, s[..., 0], c[..., 0]], -1)
    ry = torch.stack([c[..., 1], zero, s[..., 1], zero, one, zero, -s[..., 1], zero, c[..., 1]], -1)
    rz = torch.stack([c[..., 2], -s[..., 2], zero, s[..., 2], c[..., 2], zero, zero, zero, one], -1)
    shape = (*e.shape[:-1], 3, 3)
    return rz.reshape(shape) @ ry.reshape(shape) @ rx.reshape(shape)


def _rotvec_to_matrix(v: torch.Tensor) -> torch.Tensor:
    import roma

    return roma.rotvec_to_rotmat(v)


def _blender_frame(head: torch.Tensor, tail: torch.Tensor) -> torch.Tensor:
    """Rest orientation of a new Blender bone (roll 0): y along head->tail by the smallest rotation."""
    y = (tail - head) / torch.linalg.norm(tail - head)
    axis = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0], dtype=y.dtype), y)
    angle = torch.atan2(torch.linalg.norm(axis), y[1])
    return _rotvec_to_matrix(axis / torch.linalg.norm(axis).clamp_min(1e-12) * angle)


def _apply(move: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(n, 3) points moved by (n, 4, 4) rigid transforms."""
    return (points[:, None, :] @ move[:, :3, :3].transpose(1, 2))[:, 0] + move[:, :3, 3]


def _limb_chain(parent_world: torch.Tensor, rel: list[torch.Tensor], r_up: torch.Tensor, r_lo: torch.Tensor):
    """World poses of upper, upper twin, lower, lower twin and end bone for upper/lower rotations."""
    d_up = torch.eye(4, dtype=r_up.dtype).repeat(r_up.shape[0], 1, 1)
    d_lo = d_up.clone()
    d_up[:, :3, :3], d_lo[:, :3, :3] = r_up, r_lo
    w_up = parent_world @ rel[0] @ d_up
    w_up2 = w_up @ rel[1]
    w_lo = w_up2 @ rel[2] @ d_lo
    w_lo2 = w_lo @ rel[3]
    return w_up, w_up2, w_lo, w_lo2, w_lo2 @ rel[4]


def _solve_limb(
    parent_world: torch.Tensor,
    rel: list[torch.Tensor],
    reach_pos: torch.Tensor,
    bend_pos: torch.Tensor,
    is_leg: bool,
    steps: int,
) -> tuple[tuple[torch.Tensor, torch.Tensor], tuple[float, float]]:
    """Two-bone IK over all frames at once: the end joint on ``reach_pos``, the middle joint pulled
    weakly toward ``bend_pos``; knees bend about their hinge axis (x). Returns the upper and lower
    rotations and the largest reach and bend distances left."""
    n = reach_pos.shape[0]
    up_rot = torch.zeros(n, 3, dtype=torch.float64, requires_grad=True)
    lo_init = torch.zeros(n, 3, dtype=torch.float64)
    lo_init[:, 0] = 0.3 if is_leg else 0.0  # start bent the natural way
    lo_rot = lo_init.requires_grad_(True)
    hinge = torch.tensor([0.0, 1.0, 1.0] if is_leg else [0.0, 0.0, 0.0], dtype=torch.float64)
    opt = torch.optim.Adam([up_rot, lo_rot], lr=0.03)
    for _ in range(steps):
        opt.zero_grad()
        *_, w_lo, _, w_end = _limb_chain(parent_world, rel, _rotvec_to_matrix(up_rot), _rotvec_to_matrix(lo_rot))
        loss = ((w_end[:, :3, 3] - reach_pos) ** 2).sum(-1) + 0.02 * ((w_lo[:, :3, 3] - bend_pos) ** 2).sum(-1)
        loss = loss + 1e-3 * up_rot[:, 1] ** 2 + 1e-2 * ((lo_rot * hinge) ** 2).sum(-1)
        loss.sum().backward()
        opt.step()
    with torch.no_grad():
        rots = (_rotvec_to_matrix(up_rot), _rotvec_to_matrix(lo_rot))
        *_, w_lo, _, w_end = _limb_chain(parent_world, rel, *rots)
        reach = float(torch.linalg.norm(w_end[:, :3, 3] - reach_pos, dim=-1).max())
        bend = float(torch.linalg.norm(w_lo[:, :3, 3] - bend_pos, dim=-1).max())
    return rots, (reach, bend)


class Clip(NamedTuple):
    """A motion's arrays (see ``motions.Motion``): (F, J, 3) pose, (F, 3) global_orient and transl, fps."""

    pose: np.ndarray
    global_orient: np.ndarray
    transl: np.ndarray
    fps: float


def anny_walk_cycle(body: AnnyBody, n_frames: int = 40, ik_steps: int = 300) -> tuple[Clip, dict[str, float]]:
    """Anny's walk cycle resampled to ``n_frames`` frames of one loop, walking in place.

    Returns the clip and, per IK target, the largest distance (m) left between the joint and the
    target over the clip (feet and hands are reached; knee and elbow targets are only pulled toward).
    """
    doc = json.loads(walk_cycle_path().read_text())
    data = doc["animation_data"]
    model = body._model
    names = list(model.bone_labels)
    parents = list(model.bone_parents)
    idx = {n: i for i, n in enumerate(names)}
    coeffs = model.get_phenotype_blendshape_coefficients(
        **{k: torch.tensor([v], dtype=torch.float64) for k, v in body.phenotype.items()}
    )
    with torch.no_grad():
        anny_rest = model.get_rest_model(coeffs)["rest_bone_poses"][0]  # (J, 4, 4), Blender-like frames
    rest = anny_rest.clone()
    rest[0, :3, :3] = _blender_frame(*(torch.tensor(p, dtype=torch.float64) for p in (MPFB_ROOT_HEAD, MPFB_ROOT_TAIL)))
    heads = rest[:, :3, 3]
    last = max(float(f) for v in data.values() for f in v)
    t = np.arange(n_frames) * last / n_frames  # one loop; the last key repeats the first
    n, nj = n_frames, len(names)

    # Deltas (Blender pose-bone basis, in each bone's rest frame) for the keyed FK bones.
    delta = torch.eye(4, dtype=torch.float64).repeat(n, nj, 1, 1)
    for bone in FK_BONES:
        rot = torch.as_tensor(_channel(data, bone, "rotation_euler", t))
        delta[:, idx[bone], :3, :3] = _euler_xyz(rot)
        if bone == "root":
            delta[:, idx[bone], :3, 3] = torch.as_tensor(_channel(data, bone, "location", t))

    def fk(d: torch.Tensor) -> torch.Tensor:
        """World poses W_c = W_p P_p^-1 P_c D_c (Blender's pose-bone chain); W_0 = P_0 D_0."""
        rel = torch.linalg.inv(rest[parents[1:]]) @ rest[1:]
        out = [rest[0] @ d[:, 0]]
        for c in range(1, nj):
            out.append(out[parents[c]] @ rel[c - 1] @ d[:, c])
        return torch.stack(out, dim=1)

    world = fk(delta)
    reach_error: dict[str, float] = {}
    root_move = world[:, 0] @ torch.linalg.inv(rest[0])  # the root's rigid motion, frame by frame
    for bones, reach, bend in LIMBS:
        i_up, i_up2, i_lo, i_lo2, i_end = (idx[b] for b in bones)
        # Targets: IK bones posed from their rest frames (the end bone's; roll-0 at the bend joint).
        reach_pos = rest[i_end, :3, 3] + torch.as_tensor(_channel(data, reach, "location", t)) @ rest[i_end, :3, :3].T
        reach_rot = rest[i_end, :3, :3] @ _euler_xyz(torch.as_tensor(_channel(data, reach, "rotation_euler", t)))
        bend_frame = _blender_frame(heads[i_up2], heads[i_lo])
        bend_pos = heads[i_lo] + torch.as_tensor(_channel(data, bend, "location", t)) @ bend_frame.T
        # Foot and knee targets stay in the armature frame (a planted foot stays put); hand and elbow
        # targets ride on the root, as their keys (equal at both ends of a loop that moves the root by
        # a stride) show. Knee and elbow targets only say where the joint points (a weak pull).
        if "arm" in bones[0]:
            bend_pos, reach_pos = _apply(root_move, bend_pos), _apply(root_move, reach_pos)
            reach_rot = root_move[:, :3, :3] @ reach_rot
        rel = [torch.linalg.inv(rest[parents[c]]) @ rest[c] for c in (i_up, i_up2, i_lo, i_lo2, i_end)]
        rots, errors = _solve_limb(world[:, parents[i_up]], rel, reach_pos, bend_pos, "leg" in bones[0], ik_steps)
        reach_error[reach], reach_error[bend] = errors
        delta[:, i_up, :3, :3], delta[:, i_lo, :3, :3] = rots[0], rots[1]
        # The end bone copies the target's world rotation.
        base = _limb_chain(world[:, parents[i_up]], rel, *rots)[-1][:, :3, :3]
        delta[:, i_end, :3, :3] = base.transpose(1, 2) @ reach_rot
    world = fk(delta) @ torch.linalg.inv(rest) @ anny_rest  # the same skinning transforms, Anny's bone frames

    # Anny's local-ref rotations for these world poses; the root offset goes to ``transl``.
    local = model.get_pose_parameterization({"rest_bone_poses": anny_rest[None], "bone_poses": world}, "local-ref")
    import roma

    pose = roma.rotmat_to_rotvec(local[..., :3, :3]).numpy()
    orient = np.zeros((n, 3))
    posed = body.pose_batch(pose, orient, np.zeros((n, 3)))
    target_root = world[:, 0, :3, 3].numpy() @ ANNY_TO_WORLD.T
    transl = target_root - np.stack([p.bone_transforms[0][:3, 3] for p in posed])
    # The clip walks forward one stride per loop; take the progression out so that it loops in place.
    ends = torch.as_tensor(_channel(data, "root", "location", np.array([0.0, last])))
    stride = (rest[0, :3, :3] @ (ends[1] - ends[0])).numpy() @ ANNY_TO_WORLD.T
    transl -= stride[None] * (t / last)[:, None]
    floor = body.rest_vertices[:, 1].min()
    transl[:, 1] += floor - min((p.vertices[:, 1] + d[1]).min() for p, d in zip(posed, transl, strict=True))
    return Clip(pose, orient, transl, 24.0 * n_frames / last), reach_error
