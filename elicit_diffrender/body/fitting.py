"""Fit Anny (phenotype, pose, placement) to observations: 3D SMPL joints, or a photo's 2D keypoints
and silhouette.

Both fits share one differentiable Anny forward (:class:`AnnyFit`). The 3D fit matches Anny's joints
to the SMPL joints they correspond to (CLIFF's ``pred_joints``). The image fit matches projected
joints and mesh points to MediaPipe's 33 landmarks (``KEYPOINTS``; where MediaPipe places a joint
differently from Anny, shifted by ``KEYPOINT_OFFSETS``) and the mesh to the person mask
(every vertex inside the mask; every mask pixel near some vertex), coarse to fine, from two starts
(facing the camera or away) so that a mirrored body is escaped. Keypoints and a silhouette leave
depth nearly free (the body's turn about the vertical, how far a limb reaches towards the camera);
MediaPipe's metric landmarks fix it: the model's shoulder, hip and trunk lines and its visible
thighs (``WORLD_LINES``) are pulled onto theirs, as directions only (their lengths would drive the
phenotype). MediaPipe's metric shins and arms are not used: on seven synthetic subjects its shins
lean 9-16 degrees away from the true ones, always with the ankles back; on six (seeds 1-3, 9-11) its
upper arms are 6-36 degrees off and its forearms 8-56. An elbow is a hinge, so how far a forearm reaches
towards the camera shows in its foreshortening in the image, and the hinge prior says to which side;
the upper arms are held near the body's frontal plane as far as the photo is taken from the front or the back
(``ARM_PLANE_WEIGHT``; an arm raised above the shoulder only
in the silhouette stage, once its keypoints have brought it up, and so is an arm whose wrist the prior lost on the
way: ``WRIST_LOST``). Priors keep the pose
near rest (knees nearly straight, knees and elbows bending the right way) and the phenotype near
average.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage

from ..core.geometry import axis_angle_to_matrix, matrix_to_axis_angle
from .anny_model import ANNY_TO_WORLD, AnnyBody, anny_model

# SMPL joint index -> Anny joint, for the joints whose anatomy agrees between the two rigs.
SMPL_TO_ANNY = {
    0: "root", 1: "upperleg01.L", 2: "upperleg01.R", 4: "lowerleg01.L", 5: "lowerleg01.R", 7: "foot.L",
    8: "foot.R", 12: "neck01", 15: "head", 16: "upperarm01.L", 17: "upperarm01.R", 18: "lowerarm01.L",
    19: "lowerarm01.R", 20: "wrist.L", 21: "wrist.R",
}  # fmt: skip
TORSO_SMPL = (0, 1, 2, 12, 16, 17)
# A differentiable silhouette of the body through the photo's camera: camera-space vertices (V, 3) -> (H, W)
# alpha, and the factory that builds one from the mesh's faces and vertex count (``elicit prepare`` passes
# Mitsuba's; the body package itself renders nothing).
SilhouetteRender = Callable[[torch.Tensor], torch.Tensor]
SilhouetteFactory = Callable[[np.ndarray, int], SilhouetteRender]
FIT_STEPS = 240  # keypoint steps, then as many with the point-to-mask silhouette (half each)
START_YAWS = (0.0, np.pi)  # the body's turn about the vertical at the coarse stage's starts (0 faces the camera)
RENDER_STEPS = 120  # steps on the differentiable silhouette
RENDER_LR = 0.01  # Adam step size on the differentiable silhouette
RENDER_WEIGHT = 12.0  # its weight against the keypoint and prior terms
FREE_JOINTS = (
    "spine04",
    "spine03",
    "spine01",
    "neck01",
    "head",
    "clavicle.L",
    "clavicle.R",
    "upperarm01.L",
    "upperarm01.R",
    "lowerarm01.L",
    "lowerarm01.R",
    "upperleg01.L",
    "upperleg01.R",
    "lowerleg01.L",
    "lowerleg01.R",
    "foot.L",
    "foot.R",
)

# MediaPipe pose landmark index -> ("joint", Anny joint) or ("vertex", selector on the rest mesh).
KEYPOINTS = {
    0: ("vertex", "nose"), 2: ("joint", "eye.L"), 5: ("joint", "eye.R"), 7: ("vertex", "ear.L"),
    8: ("vertex", "ear.R"), 11: ("joint", "upperarm01.L"), 12: ("joint", "upperarm01.R"),
    13: ("joint", "lowerarm01.L"), 14: ("joint", "lowerarm01.R"), 15: ("joint", "wrist.L"),
    16: ("joint", "wrist.R"), 23: ("joint", "upperleg01.L"), 24: ("joint", "upperleg01.R"),
    25: ("joint", "lowerleg01.L"), 26: ("joint", "lowerleg01.R"), 27: ("joint", "foot.L"), 28: ("joint", "foot.R"),
    29: ("vertex", "heel.L"), 30: ("vertex", "heel.R"), 31: ("vertex", "toe.L"), 32: ("vertex", "toe.R"),
}  # fmt: skip
# Where MediaPipe puts a joint landmark, relative to Anny's joint head: (bone, offset in that bone's frame, m;
# +y runs along the bone). Measured on 48 synthetic views of four Anny subjects (``elicit synth`` seeds 4-7,
# front +-50 degrees) by least squares on the 2D error, left and right mirrored: MediaPipe's ankle sits 2.4 cm
# above Anny's foot joint and its hip 2.2 cm below Anny's hip joint; without the offsets the fit tips the legs
# out of the image plane to shorten them. Mean error over those views 5.0 -> 3.2 px (hips), 5.7 -> 2.2 px
# (ankles), 9.0 -> 3.3 px (elbows), 5.6 -> 2.8 px (shoulders); knees, wrists, heels and toes showed no
# consistent offset (a robust refit found none there either, and moved these by under 0.7 cm).
KEYPOINT_OFFSETS = {
    11: ("upperarm01.L", (-0.015, -0.013, 0.006)), 12: ("upperarm01.R", (0.015, -0.013, 0.006)),
    13: ("lowerarm01.L", (0.0, -0.025, 0.033)), 14: ("lowerarm01.R", (0.0, -0.025, 0.033)),
    23: ("upperleg01.L", (-0.004, 0.022, -0.021)), 24: ("upperleg01.R", (0.004, 0.022, -0.021)),
    27: ("lowerleg01.L", (0.005, -0.024, 0.006)), 28: ("lowerleg01.R", (-0.005, -0.024, 0.006)),
}  # fmt: skip
TORSO_KEYPOINTS = (11, 12, 23, 24)
WORLD_WEIGHT = 1.0  # weight of the metric-landmark direction term against the keypoint term
# The body's lines that MediaPipe's metric landmarks fix: name -> (from, to), each the mean of landmarks.
WORLD_LINES = {
    "shoulders": ((12,), (11,)), "hips": ((24,), (23,)), "trunk": ((23, 24), (11, 12)),
    "left_thigh": ((23,), (25,)), "right_thigh": ((24,), (26,)),
}  # fmt: skip
TORSO_LINES = ("shoulders", "hips", "trunk")  # the lines the coarse (placement-only) stage matches
# Bending the wrong way costs: the knee's flexion axis is +x (world), the elbow's -x in the rest frame.
HINGES = {"lowerleg01.L": 1.0, "lowerleg01.R": 1.0, "lowerarm01.L": -1.0, "lowerarm01.R": -1.0}
# Extra cost on knee rotation (rad^2, inside ``prior``): a few pixels of knee or foot landmark error would
# otherwise bend the knees 10-20 degrees out of the image plane (measured on the synthetic subjects; 400 left
# the knees 1-3 cm nearer their true depth than 100 on the photo-path benchmark's subjects).
KNEE_WEIGHT = 400.0
KNEE_WEIGHT_NOT_STANDING = 1.0  # a photo of someone seated, kneeling or mid-stride shows bent knees: no such prior
# Cost of each upper arm leaving the body's frontal plane (the square of its direction's component along the
# torso's normal), times the square of the normal's component along the camera's axis. Nothing in one photo says
# how far an upper arm reaches towards or away from the camera: MediaPipe's metric upper arms were 6-36 degrees off
# the true ones on six synthetic subjects (0.5-20 with this prior and no metric arms). A photo from the side shows
# that reach; held there at full weight, the prior turned side-view bodies 15-36 degrees towards the camera (five
# multi-photo subjects' side photos).
ARM_PLANE_WEIGHT = 1.0
# A standing person (``standing``): each leg's knee at least STANDING_DROP torso lengths below its hip and its ankle
# as far below its knee, in the image. Only then are the knees held nearly straight and the trunk upright (below).
STANDING_DROP = 0.55
# An upper arm shorter than this many torso lengths in the image reaches towards or away from the camera: the
# frontal-plane prior is not applied to it (an arm held out to the camera, a hand on the far hip).
ARM_FORESHORTENED = 0.35
# A wrist this many torso lengths from its keypoint after the first fine stage was lost to the frontal-plane prior:
# held from the start, the prior can fold a forearm while the upper arm swings into the plane, and the robust
# keypoint term no longer pulls a wrist that far back (fs0000, arms hanging straight: 183 px from its keypoint, 148
# at the end; its lost wrists then fitted to 3 px). That stage is run again with the arm held only later.
WRIST_LOST = 0.25
# A standing person's spine (pelvis to neck) leans towards or away from the camera as much as their thighs do
# (``AnnyFit.uprightness``): the keypoints, the silhouette and MediaPipe's metric trunk otherwise let the spine bend
# back while the collarbones bring the shoulders forward, or lean the whole trunk 10-20 degrees towards the camera.
UPRIGHT_WEIGHT = 1.0
# MediaPipe's metric trunk is taken for wrong, and the spine held to the thighs, only where its lean towards the
# camera differs from its thighs' by more than this (its errors on the test subjects: 14-23 degrees; a hip sway or
# a slight stoop stays below).
UPRIGHT_TRIGGER_DEG = 10.0
# Cost of each shin leaving the image plane (the square of its direction's component along the camera's axis),
# for a person not standing whose shin the image shows at length (its knee-to-ankle line at least SHIN_AT_LENGTH
# torso lengths long): a seated person's shins, whose tilt towards the camera nothing else in one photo fixes
# (``seated``, synthetic: 40-45 degrees off, feet pushed towards the camera). A shin stretched towards the camera
# is short in the image and stays free; one stretched sideways is at length and in the image plane.
SHIN_PLANE_WEIGHT = 1.0
SHIN_AT_LENGTH = 0.55
ARMS = (("upperarm01.L", "lowerarm01.L"), ("upperarm01.R", "lowerarm01.R"))  # shoulder and elbow joints
LEGS = (("upperleg01.L", "lowerleg01.L"), ("upperleg01.R", "lowerleg01.R"))  # hip and knee joints


def procrustes(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising |R src + t - dst| (no scale, no reflection)."""
    cs, cd = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((dst - cd).T @ (src - cs))
    d = np.sign(np.linalg.det(u @ vt))
    rot = u @ np.diag([1.0, 1.0, d]) @ vt
    return rot, cd - rot @ cs


def select_vertices(rest: np.ndarray, parts: np.ndarray, head_part: int, shin_parts: tuple[int, int]) -> dict:
    """Rest-mesh vertex indices for the landmarks that are not joints (world frame: +y up, +z front)."""
    head = np.nonzero(parts == head_part)[0]
    hv = rest[head]
    centre_y = hv[:, 1].min() + 0.55 * np.ptp(hv[:, 1])
    band = np.abs(hv[:, 1] - centre_y) < 0.04
    out = {
        "nose": int(head[np.argmax(hv[:, 2] - 5 * np.abs(hv[:, 0]))]),
        "ear.L": int(head[band][np.argmax(hv[band, 0])]),
        "ear.R": int(head[band][np.argmin(hv[band, 0])]),
    }
    for side, part in zip(("L", "R"), shin_parts, strict=True):
        idx = np.nonzero(parts == part)[0]
        v = rest[idx]
        low = v[:, 1] < v[:, 1].min() + 0.04
        out[f"heel.{side}"] = int(idx[low][np.argmin(v[low, 2])])
        out[f"toe.{side}"] = int(idx[low][np.argmax(v[low, 2])])
    return out


class AnnyFit(torch.nn.Module):
    """Differentiable Anny: free-joint rotations, phenotype logits and a global rigid placement."""

    def __init__(self) -> None:
        super().__init__()
        model = anny_model()
        self.model = model
        self.names = list(model.bone_labels)
        self.labels = list(model.phenotype_labels)
        self.free = torch.tensor([self.names.index(n) for n in FREE_JOINTS])
        self.knees = [FREE_JOINTS.index(n) for n in ("lowerleg01.L", "lowerleg01.R")]
        self.torso_joints = [
            self.names.index(n) for n in ("upperarm01.L", "upperarm01.R", "upperleg01.L", "upperleg01.R")
        ]
        self.arm_joints = torch.tensor([[self.names.index(n) for n in arm] for arm in ARMS])  # (2, shoulder/elbow)
        self.spine_ends = [self.names.index(n) for n in ("root", "neck01")]
        self.legs = torch.tensor([[self.names.index(n) for n in leg] for leg in LEGS])  # (2, hip/knee)
        self.feet = [self.names.index(n) for n in ("foot.L", "foot.R")]
        self.shins_in_plane = torch.zeros(2, dtype=torch.float64)  # which shins the image-plane prior holds
        self.knee_weight = KNEE_WEIGHT
        self.arms_in_plane = torch.ones(2, dtype=torch.float64)  # which arms the frontal-plane prior holds
        self.rotvecs = torch.nn.Parameter(torch.zeros(len(FREE_JOINTS), 3, dtype=torch.float64))
        self.pheno = torch.nn.Parameter(torch.zeros(len(self.labels), dtype=torch.float64))
        self.g_rot = torch.nn.Parameter(torch.zeros(3, dtype=torch.float64))
        self.g_t = torch.nn.Parameter(torch.zeros(3, dtype=torch.float64))
        a4 = torch.eye(4, dtype=torch.float64)
        a4[:3, :3] = torch.as_tensor(ANNY_TO_WORLD)
        self.register_buffer("a4", a4)

    def forward(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """World vertices (V, 3), joint heads (J, 3) and bone rotations (J, 3, 3) after the global placement."""
        params = torch.eye(4, dtype=torch.float64).repeat(1, len(self.names), 1, 1)
        full = torch.zeros(len(self.names), 3, dtype=torch.float64).index_copy(0, self.free, self.rotvecs)
        params = params.clone()
        params[0, :, :3, :3] = axis_angle_to_matrix(full)
        pheno = {k: torch.sigmoid(self.pheno[i])[None] for i, k in enumerate(self.labels)}
        out = self.model(pose_parameters=params, phenotype_kwargs=pheno)
        rot = axis_angle_to_matrix(self.g_rot)
        verts = out["vertices"][0] @ self.a4[:3, :3].T @ rot.T + self.g_t
        frames = self.a4 @ out["bone_poses"][0]
        return verts, frames[:, :3, 3] @ rot.T + self.g_t, rot @ frames[:, :3, :3]

    def prior(self) -> torch.Tensor:
        bend = torch.zeros((), dtype=torch.float64)
        for name, sign in HINGES.items():
            k = FREE_JOINTS.index(name)
            axis = torch.as_tensor(ANNY_TO_WORLD.T @ np.array([1.0, 0.0, 0.0]))
            bend = bend + F.relu(-sign * (self.rotvecs[k] @ axis)) ** 2
        knees = (self.rotvecs[self.knees] ** 2).sum()
        return (self.rotvecs**2).sum() + 0.5 * (self.pheno**2).sum() + 10.0 * bend + self.knee_weight * knees

    def arm_plane(self, heads: torch.Tensor, which: torch.Tensor | None = None) -> torch.Tensor:
        """How far the upper arms leave the torso's frontal plane where the photo cannot show it: the sum over the
        arms ``arms_in_plane`` (or ``which``, (2,) weights) holds of the squared component of the shoulder -> elbow
        direction along the plane's normal ``n`` (the shoulder line crossed with the trunk, from the joint ``heads``
        (J, 3)), times ``n_z^2`` (camera space, held fixed): how much of the normal lies along the camera's axis. A
        photo from the front or the back cannot show an arm's reach along the normal; one from the side shows it
        (a swing in a walk, a reach forward), and there the prior would turn the whole body instead."""
        left, right, hip_left, hip_right = heads[self.torso_joints]
        normal = torch.linalg.cross(left - right, (left + right) / 2 - (hip_left + hip_right) / 2)
        normal = normal / normal.norm().clamp(min=1e-9)
        arms = heads[self.arm_joints[:, 1]] - heads[self.arm_joints[:, 0]]
        arms = arms / arms.norm(dim=1, keepdim=True).clamp(min=1e-9)
        unseen = normal[2].detach() ** 2
        return unseen * ((self.arms_in_plane if which is None else which) * (arms @ normal) ** 2).sum()

    def shin_plane(self, heads: torch.Tensor) -> torch.Tensor:
        """How far the shins that ``shins_in_plane`` holds leave the image plane: the squared component of each
        knee -> ankle direction along the camera's axis (camera space: z), from the joint ``heads`` (J, 3)."""
        shins = heads[self.feet] - heads[self.legs[:, 1]]
        shins = shins / shins.norm(dim=1, keepdim=True).clamp(min=1e-9)
        return (self.shins_in_plane * shins[:, 2] ** 2).sum()

    def uprightness(self, heads: torch.Tensor) -> torch.Tensor:
        """The squared difference between how far the spine (pelvis to neck) and the thighs (knees to hips) point
        along the camera's axis (camera space: z away from the camera), from the joint ``heads`` (J, 3)."""
        pelvis, neck = heads[self.spine_ends]
        spine = (neck - pelvis) / (neck - pelvis).norm().clamp(min=1e-9)
        thighs = heads[self.legs[:, 0]] - heads[self.legs[:, 1]]
        thighs = thighs / thighs.norm(dim=1, keepdim=True).clamp(min=1e-9)
        return (spine[2] - thighs[:, 2].mean()) ** 2

    def result(self) -> dict:
        pose = np.zeros((len(self.names), 3))
        pose[self.free.numpy()] = self.rotvecs.detach().numpy()
        phenotype = {k: float(torch.sigmoid(self.pheno[i].detach())) for i, k in enumerate(self.labels)}
        return {
            "phenotype": phenotype,
            "pose": pose,
            "global_orient": self.g_rot.detach().numpy().copy(),
            "transl": self.g_t.detach().numpy().copy(),
        }


class KeypointModel:
    """Anny's counterparts of MediaPipe's landmarks (``KEYPOINTS``): joint heads shifted by ``KEYPOINT_OFFSETS``
    in their bone's frame, or points of the mesh. ``ids`` are the landmark indices, in the order returned."""

    def __init__(self, fit: AnnyFit) -> None:
        from .base import PART_NAMES

        body0 = AnnyBody()
        vsel = select_vertices(
            body0.rest_vertices,
            body0.vertex_parts(),
            PART_NAMES.index("head"),
            (PART_NAMES.index("left_shin"), PART_NAMES.index("right_shin")),
        )
        self.ids = list(KEYPOINTS)
        joint = [fit.names.index(name) if kind == "joint" else -1 for kind, name in KEYPOINTS.values()]
        vertex = [vsel[name] if kind == "vertex" else -1 for kind, name in KEYPOINTS.values()]
        self.joint, self.vertex = torch.tensor(joint), torch.tensor(vertex)
        self.frame = torch.tensor(
            [fit.names.index(KEYPOINT_OFFSETS[k][0]) if k in KEYPOINT_OFFSETS else 0 for k in self.ids]
        )
        self.offset = torch.tensor(
            [KEYPOINT_OFFSETS[k][1] if k in KEYPOINT_OFFSETS else (0.0, 0.0, 0.0) for k in self.ids],
            dtype=torch.float64,
        )
        self.is_joint = self.joint >= 0

    def __call__(self, verts: torch.Tensor, heads: torch.Tensor, rots: torch.Tensor) -> torch.Tensor:
        """(len(ids), 3) landmark positions of the posed body (``AnnyFit``'s outputs)."""
        at_joint = heads[self.joint.clamp(min=0)] + (rots[self.frame] @ self.offset[:, :, None])[:, :, 0]
        return torch.where(self.is_joint[:, None], at_joint, verts[self.vertex.clamp(min=0)])


def _optimise(fit: AnnyFit, params: list, loss_fn, steps: int, lr: float) -> float:
    opt = torch.optim.Adam(params, lr=lr)
    loss = torch.zeros(())
    for step in range(steps):
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        opt.step()
        if step == int(steps * 0.7):
            for g in opt.param_groups:
                g["lr"] = lr * 0.3
    return float(loss.detach())


def fit_anny_to_smpl_joints(target: np.ndarray, steps: int = 300) -> dict:
    """Fit Anny to (24+, 3) SMPL joints in any world frame; adds the per-joint error (m) and the body."""
    target = np.asarray(target, dtype=np.float64)[:24]
    if target.shape != (24, 3) or not np.isfinite(target).all():
        raise ValueError(f"expected 24 finite SMPL joints (24, 3), got {target.shape}")
    fit = AnnyFit()
    smpl_ids = list(SMPL_TO_ANNY)
    anny_ids = [fit.names.index(SMPL_TO_ANNY[i]) for i in smpl_ids]
    with torch.no_grad():
        _, heads, _ = fit()
    torso = [smpl_ids.index(i) for i in TORSO_SMPL]
    rot, t = procrustes(heads[anny_ids].numpy()[torso], target[smpl_ids][torso])
    with torch.no_grad():
        fit.g_rot.copy_(matrix_to_axis_angle(torch.as_tensor(rot)))
        fit.g_t.copy_(torch.as_tensor(t))
    goal = torch.as_tensor(target[smpl_ids])

    def loss():
        _, heads, _ = fit()
        return ((heads[anny_ids] - goal) ** 2).sum(1).mean() + 1e-4 * fit.prior()

    _optimise(fit, list(fit.parameters()), loss, steps, 0.03)
    with torch.no_grad():
        _, heads, _ = fit()
        err = (heads[anny_ids] - goal).norm(dim=1).numpy()
    out = fit.result()
    return {**out, "joint_error_m": err, "body": AnnyBody(out["phenotype"])}


class ImageTargets:
    """What the image fit matches: the camera, landmarks and the mask (with its distance fields)."""

    def __init__(
        self, K: np.ndarray, mask: np.ndarray, keypoints: np.ndarray | None, n_mask_samples: int = 1500, seed: int = 0
    ) -> None:
        self.K = torch.as_tensor(K, dtype=torch.float64)
        self.h, self.w = mask.shape
        self.mask = mask
        outside = ndimage.distance_transform_edt(~mask)  # pixels to the mask, 0 inside
        self.outside = torch.as_tensor(outside, dtype=torch.float64)[None, None]
        ys, xs = np.nonzero(mask)
        rng = np.random.default_rng(seed)
        pick = rng.choice(xs.size, size=min(n_mask_samples, xs.size), replace=False)
        self.mask_pixels = torch.as_tensor(np.stack([xs[pick] + 0.5, ys[pick] + 0.5], 1), dtype=torch.float64)
        self.keypoints = None if keypoints is None else torch.as_tensor(keypoints, dtype=torch.float64)
        self.scale = float(max(self.h, self.w))

    def project(self, x: torch.Tensor) -> torch.Tensor:
        uv = x @ self.K.T
        return uv[:, :2] / uv[:, 2:].clamp(min=1e-3)

    def sample_outside(self, uv: torch.Tensor) -> torch.Tensor:
        norm = torch.stack([uv[:, 0] / self.w * 2 - 1, uv[:, 1] / self.h * 2 - 1], -1).reshape(1, 1, -1, 2)
        return F.grid_sample(self.outside, norm, mode="bilinear", padding_mode="border", align_corners=False).reshape(
            -1
        )


def _rendered_silhouette_loss(fit: AnnyFit, mask: np.ndarray, render: SilhouetteRender, other):
    """``other() + RENDER_WEIGHT * mean((A - M)^2)`` with A the body's rendered silhouette and M the mask
    resized to A's resolution."""
    target: torch.Tensor | None = None

    def loss():
        nonlocal target
        verts, _, _ = fit()
        alpha = render(verts)
        if target is None:
            target = F.interpolate(
                torch.as_tensor(mask, dtype=torch.float32)[None, None], size=tuple(alpha.shape), mode="area"
            )[0, 0]
        return other() + RENDER_WEIGHT * ((alpha - target) ** 2).mean()

    return loss


def line_directions(points: dict[int, torch.Tensor], names) -> torch.Tensor:
    """Unit directions (N, 3) of the ``WORLD_LINES`` named ``names``, from landmark index -> (3,) point."""
    lines = []
    for name in names:
        start, end = (torch.stack([points[k] for k in ends]).mean(0) for ends in WORLD_LINES[name])
        lines.append(end - start)
    out = torch.stack(lines)
    return out / out.norm(dim=1, keepdim=True).clamp(min=1e-9)


def _visible(keypoints: np.ndarray, ids) -> bool:
    return bool((keypoints[list(ids), 2] > 0.5).all())


def torso_length_px(keypoints: np.ndarray) -> float:
    """Pixels from the hips' midpoint to the shoulders' in the image."""
    return float(np.linalg.norm(keypoints[[11, 12], :2].mean(0) - keypoints[[23, 24], :2].mean(0)))


def standing(keypoints: np.ndarray | None) -> bool:
    """Whether MediaPipe's 2D landmarks (33, 3) show a standing person: each knee well below its hip and each
    ankle well below its knee, in torso lengths (``STANDING_DROP``; image y grows downwards)."""
    if keypoints is None or not _visible(keypoints, (11, 12, 23, 24, 25, 26, 27, 28)):
        return False
    torso = torso_length_px(keypoints)
    y = keypoints[:, 1]
    return bool(all(y[k] - y[h] > STANDING_DROP * torso and y[a] - y[k] > STANDING_DROP * torso
                    for h, k, a in ((23, 25, 27), (24, 26, 28))))  # fmt: skip


def segments_at_length(
    keypoints: np.ndarray | None, pairs: tuple[tuple[int, int], tuple[int, int]], torso_lengths: float
) -> np.ndarray:
    """(2,) 1 for each of the (left, right) landmark ``pairs`` the image shows at least ``torso_lengths`` torso
    lengths long, 0 for one shorter (foreshortened) or not seen."""
    out = np.zeros(2)
    if keypoints is None or not _visible(keypoints, (11, 12, 23, 24)):
        return out
    torso = torso_length_px(keypoints)
    for side, (a, b) in enumerate(pairs):
        length = np.linalg.norm(keypoints[b, :2] - keypoints[a, :2])
        out[side] = float(_visible(keypoints, (a, b)) and length >= torso_lengths * torso)
    return out


def arms_in_image_plane(keypoints: np.ndarray | None) -> np.ndarray:
    """(2,) 1 for each upper arm (left, right) that the image shows at length (``ARM_FORESHORTENED``), 0 for one
    foreshortened or not seen."""
    return segments_at_length(keypoints, ((11, 13), (12, 14)), ARM_FORESHORTENED)


def shins_at_length(keypoints: np.ndarray | None) -> np.ndarray:
    """(2,) 1 for each shin (left, right) that the image shows at length (``SHIN_AT_LENGTH`` torso lengths from
    knee to ankle), 0 for one foreshortened or not seen."""
    return segments_at_length(keypoints, ((25, 27), (26, 28)), SHIN_AT_LENGTH)


def arms_raised(keypoints: np.ndarray) -> np.ndarray:
    """(2,) bool for each arm (left, right) whose elbow the image shows above its shoulder (image y grows
    downwards). Such an arm swings far from the rest pose while the fit follows its keypoints; the frontal-plane
    prior holds it only once it is there, in the silhouette stage: held from the start, it left the raised left
    arm of ``arms_raised`` (synthetic) at its side, its wrist 144 px from the keypoint."""
    pairs = ((11, 13), (12, 14))
    return np.array([bool(_visible(keypoints, (s, e)) and keypoints[e, 1] < keypoints[s, 1]) for s, e in pairs])


def wrists_lost(keypoints: np.ndarray, wrists: np.ndarray, held: np.ndarray) -> np.ndarray:
    """(2,) bool for each arm (left, right) that the frontal-plane prior holds (``held``, (2,) bool) and whose
    model wrist (``wrists``, (2, 2) pixels) lies more than ``WRIST_LOST`` torso lengths from its seen keypoint."""
    out = np.zeros(2, dtype=bool)
    if not _visible(keypoints, (11, 12, 23, 24)):
        return out
    reach = WRIST_LOST * torso_length_px(keypoints)
    for side, k in enumerate((15, 16)):
        far = np.linalg.norm(wrists[side] - keypoints[k, :2]) > reach
        out[side] = bool(held[side] and _visible(keypoints, (k,)) and far)
    return out


def upright_trunk(trunk: torch.Tensor, thighs: list[torch.Tensor]) -> torch.Tensor:
    """MediaPipe's metric trunk direction (hips to shoulders; camera axes: x right, y down, z away) with its lean
    towards the camera replaced by its thighs' mean (each hip to knee, so taken reversed): a standing person's
    trunk and thighs are upright together. Its metric trunk leans
    towards the camera by 14-23 degrees on three of eight standing test subjects whose trunks are upright, while its
    metric thighs stay within 4 degrees of theirs."""

    def lean(d: torch.Tensor) -> torch.Tensor:  # towards the camera, from up
        return torch.atan2(-d[2], -d[1])

    target = torch.stack([lean(-d) for d in thighs]).mean()
    r = torch.sqrt(trunk[1] ** 2 + trunk[2] ** 2)
    out = torch.stack([trunk[0], -r * torch.cos(target), -r * torch.sin(target)])
    return out / out.norm().clamp(min=1e-9)


def fit_anny_to_image(
    K: np.ndarray,
    mask: np.ndarray,
    keypoints: np.ndarray | None,
    joints3d: np.ndarray | None = None,
    steps: int = FIT_STEPS,
    render_silhouette: SilhouetteFactory | None = None,
    render_steps: int = RENDER_STEPS,
    world_landmarks: np.ndarray | None = None,
    phenotype: dict[str, float] | None = None,
) -> dict:
    """Fit Anny to one photo in camera space (``x_cam = x_world``): 2D keypoints (33, 3: x, y,
    visibility, pixels) and/or camera-space SMPL joints, then the silhouette: first a fast
    point-to-mask distance, then ``render_steps`` steps on the differentiable silhouette that
    ``render_silhouette(faces, n_vertices)`` renders (skipped without one). ``world_landmarks`` (33, 3),
    MediaPipe's metric landmarks in camera axes, fix the directions of the body's ``WORLD_LINES``: the torso's
    from the coarse stage on, the visible arms' and thighs' in the fine stages (``WORLD_WEIGHT``). A given
    ``phenotype`` (another photo's fit of the same person) holds the body's shape fixed: only pose and placement
    are fitted."""
    if keypoints is None and joints3d is None:
        raise ValueError("the image fit needs 2D keypoints or 3D joints")
    targets = ImageTargets(K, mask, keypoints)
    fit = AnnyFit()
    shape_logits = torch.zeros_like(fit.pheno)
    if phenotype is not None:
        values = torch.tensor([phenotype[k] for k in fit.labels], dtype=torch.float64).clamp(1e-4, 1 - 1e-4)
        shape_logits = torch.logit(values)
        fit.pheno.requires_grad_(False)
    model_keypoints = KeypointModel(fit)
    kp_ids = model_keypoints.ids
    # Posture priors only where the photo shows the posture they assume (3D joints alone keep them all).
    is_standing = standing(keypoints) if keypoints is not None else True
    hold_upright = False  # set below where MediaPipe's metric trunk leans away from its own thighs
    fit.knee_weight = KNEE_WEIGHT if is_standing else KNEE_WEIGHT_NOT_STANDING
    arms_lowered = None  # the arms the frontal-plane prior holds from the start (``arms_raised``)
    if keypoints is not None:
        fit.arms_in_plane = torch.as_tensor(arms_in_image_plane(keypoints))
        if not is_standing:  # a standing person's knees are held straight instead (``KNEE_WEIGHT``)
            fit.shins_in_plane = torch.as_tensor(shins_at_length(keypoints))
        raised = arms_raised(keypoints)
        arms_lowered = fit.arms_in_plane * torch.as_tensor(~raised, dtype=torch.float64)
        goal = targets.keypoints[kp_ids]
        vis = (goal[:, 2] > 0.5).double()
        torso_rows = torch.tensor([kp_ids.index(k) for k in TORSO_KEYPOINTS])
    smpl_ids = list(SMPL_TO_ANNY)
    anny_ids = [fit.names.index(SMPL_TO_ANNY[i]) for i in smpl_ids]

    def kp_loss(verts, heads, rots, rows=None):
        uv = targets.project(model_keypoints(verts, heads, rots))
        d = ((uv - goal[:, :2]) / targets.scale).pow(2).sum(1)
        robust = d / (d + 0.02**2)  # Geman-McClure, 2% of the image as scale
        w = vis if rows is None else vis * torch.zeros_like(vis).index_fill(0, rows, 1.0)
        return (robust * w).sum() / w.sum().clamp(min=1)

    # Lines whose landmarks are all visible in the photo (the torso's always count).
    used = {k for ends in WORLD_LINES.values() for e in ends for k in e}
    seen = {k for k in used if keypoints is None or keypoints[k, 2] > 0.5}
    lines_used = [n for n, ends in WORLD_LINES.items() if n in TORSO_LINES or set(ends[0] + ends[1]) <= seen]
    world_goal = None
    if world_landmarks is not None:
        world = torch.as_tensor(np.asarray(world_landmarks), dtype=torch.float64)
        directions = line_directions({k: world[k] for k in used}, lines_used)
        world_goal = dict(zip(lines_used, directions, strict=True))
        if is_standing and {"left_thigh", "right_thigh"} <= set(world_goal):
            thighs = [world_goal["left_thigh"], world_goal["right_thigh"]]
            upright = upright_trunk(world_goal["trunk"], thighs)
            if torch.rad2deg(torch.arccos((upright @ world_goal["trunk"]).clamp(-1, 1))) > UPRIGHT_TRIGGER_DEG:
                world_goal["trunk"], hold_upright = upright, True

    def model_lines(verts, heads, rots, names) -> torch.Tensor:
        kp = model_keypoints(verts, heads, rots)
        return line_directions({k: kp[kp_ids.index(k)] for k in used}, names)

    def world_loss(verts, heads, rots, names=None):
        """``sum (1 - cos(model line, MediaPipe line))`` over the lines ``names`` (default: every usable
        one); 0 without metric landmarks."""
        if world_goal is None:
            return torch.zeros((), dtype=torch.float64)
        names = lines_used if names is None else names
        goal = torch.stack([world_goal[n] for n in names])
        return (1.0 - (model_lines(verts, heads, rots, names) * goal).sum(1)).sum()

    def j3_loss(heads):
        return ((heads[anny_ids] - torch.as_tensor(joints3d[:24][smpl_ids])) ** 2).sum(1).mean()

    def silhouette(verts):
        uv = targets.project(verts)
        inside = (targets.sample_outside(uv) / targets.scale).pow(2).mean()
        sub = uv[::4]
        d = torch.cdist(targets.mask_pixels, sub).min(1).values / targets.scale
        return inside + d.pow(2).mean()

    # Start: upright and facing the camera (or away), placed at the depth the torso's size implies.
    base = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # body +y up -> image up; body front -> camera
    best = None
    for yaw in START_YAWS:
        with torch.no_grad():
            fit.rotvecs.zero_()
            fit.pheno.copy_(shape_logits)
            rot = base @ axis_angle_to_matrix(torch.tensor([0.0, yaw, 0.0], dtype=torch.float64)).numpy()
            fit.g_rot.copy_(matrix_to_axis_angle(torch.as_tensor(rot)))
            fit.g_t.zero_()
            verts, heads, rots = fit()
        if joints3d is not None:
            r, t = procrustes(
                heads[anny_ids].numpy()[[smpl_ids.index(i) for i in TORSO_SMPL]],
                np.asarray(joints3d)[:24][smpl_ids][[smpl_ids.index(i) for i in TORSO_SMPL]],
            )
            with torch.no_grad():
                fit.g_rot.copy_(matrix_to_axis_angle(torch.as_tensor(r @ rot)))
                fit.g_t.copy_(torch.as_tensor(t))
        else:
            ys, xs = np.nonzero(mask)
            height_px = max(ys.max() - ys.min(), 1)
            height_m = float(np.ptp(verts[:, 1].numpy()))
            z = float(K[1, 1]) * height_m / height_px
            cx, cy = (xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2
            centre = np.linalg.inv(K) @ np.array([cx, cy, 1.0]) * z
            with torch.no_grad():
                fit.g_t.copy_(torch.as_tensor(centre) - verts.mean(0) + fit.g_t)

        def coarse():
            verts, heads, rots = fit()
            loss = j3_loss(heads) if joints3d is not None else kp_loss(verts, heads, rots, torso_rows)
            return loss + WORLD_WEIGHT * world_loss(verts, heads, rots, TORSO_LINES) + 1e-3 * (fit.pheno**2).sum()

        loss = _optimise(fit, [fit.g_rot, fit.g_t, fit.pheno], coarse, 60, 0.05)
        if keypoints is not None:
            with torch.no_grad():
                verts, heads, rots = fit()
                loss = float(kp_loss(verts, heads, rots) + WORLD_WEIGHT * world_loss(verts, heads, rots, TORSO_LINES))
        if best is None or loss < best[0]:
            best = (loss, {k: v.detach().clone() for k, v in fit.state_dict().items()}, yaw)
    fit.load_state_dict(best[1])

    def fine(with_silhouette: bool):
        def loss():
            verts, heads, rots = fit()
            total = 1e-3 * fit.prior() + WORLD_WEIGHT * world_loss(verts, heads, rots)
            total = total + ARM_PLANE_WEIGHT * fit.arm_plane(heads, None if with_silhouette else arms_lowered)
            total = total + SHIN_PLANE_WEIGHT * fit.shin_plane(heads)
            if hold_upright:
                total = total + UPRIGHT_WEIGHT * fit.uprightness(heads)
            if keypoints is not None:
                total = total + kp_loss(verts, heads, rots)
            if joints3d is not None:
                total = total + 10.0 * j3_loss(heads)
            if with_silhouette:
                total = total + 6.0 * silhouette(verts)
            return total

        return loss

    before = {k: v.detach().clone() for k, v in fit.state_dict().items()}
    _optimise(fit, list(fit.parameters()), fine(False), steps // 2, 0.02)
    released = np.zeros(2, dtype=bool)
    if keypoints is not None:
        with torch.no_grad():
            uv = targets.project(model_keypoints(*fit())).numpy()
        released = wrists_lost(keypoints, uv[[kp_ids.index(15), kp_ids.index(16)]], arms_lowered.numpy() > 0)
        if released.any():
            arms_lowered = arms_lowered * torch.as_tensor(~released, dtype=torch.float64)
            fit.load_state_dict(before)
            _optimise(fit, list(fit.parameters()), fine(False), steps // 2, 0.02)
    _optimise(fit, list(fit.parameters()), fine(True), steps // 2, 0.01)
    if render_silhouette is not None and render_steps > 0:
        faces = fit.model.get_triangular_faces().cpu().numpy()
        render = render_silhouette(faces, int(fit.model.template_vertices.shape[-2]))
        _optimise(fit, list(fit.parameters()), _rendered_silhouette_loss(fit, mask, render, fine(False)),
                  render_steps, RENDER_LR)  # fmt: skip
    with torch.no_grad():
        verts, heads, rots = fit()
        report = {"standing": is_standing, "held_upright": hold_upright, "arms_in_plane": fit.arms_in_plane.tolist(),
                  "shins_in_plane": fit.shins_in_plane.tolist(),
                  "start_yaw_deg": round(float(np.degrees(best[2])))}  # fmt: skip
        if keypoints is not None:
            report["arms_raised"], report["arms_released"] = raised.tolist(), released.tolist()
            uv = targets.project(model_keypoints(verts, heads, rots))
            err = (uv - goal[:, :2]).norm(dim=1)[vis > 0].numpy()
            report["keypoint_error_px"] = {
                "median": float(np.median(err)),
                "mean": float(err.mean()),
                "per_keypoint": {int(k): float(e) for k, e in zip(np.array(kp_ids)[vis.numpy() > 0], err, strict=True)},
            }
        if world_goal is not None:
            goal_lines = torch.stack([world_goal[n] for n in lines_used])
            cos = (model_lines(verts, heads, rots, lines_used) * goal_lines).sum(1)
            angles = torch.rad2deg(torch.arccos(cos.clamp(-1, 1))).numpy()
            report["line_direction_error_deg"] = dict(zip(lines_used, map(float, angles), strict=True))
        if joints3d is not None:
            report["joint_error_mm"] = float(
                np.median((heads[anny_ids] - torch.as_tensor(np.asarray(joints3d)[:24][smpl_ids])).norm(dim=1).numpy())
                * 1000
            )
    out = fit.result()
    return {**out, "report": report, "body": AnnyBody(out["phenotype"])}


def triangulate(
    projections: np.ndarray, keypoints: np.ndarray, threshold: float, min_visibility: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """World points (L, 3) of landmarks seen in several views, and how many views agree on each (0: none).

    ``projections`` (N, 3, 4) are ``K [R | T]``; ``keypoints`` (N, L, 3) hold x, y (pixels) and visibility.
    Per landmark, every pair of views where it is visible proposes a point (linear triangulation); the one
    that most views reproject within ``threshold`` pixels wins (a detector that swaps left and right in a
    rear view is outvoted), and the point is re-triangulated from those views."""

    def solve(views: list[int], k: int) -> np.ndarray:
        rows = []
        for v in views:
            x, y = keypoints[v, k, :2]
            rows += [x * projections[v, 2] - projections[v, 0], y * projections[v, 2] - projections[v, 1]]
        _, _, vt = np.linalg.svd(np.asarray(rows))
        return vt[-1, :3] / vt[-1, 3] if abs(vt[-1, 3]) > 1e-12 else np.full(3, np.nan)

    def errors(point: np.ndarray, k: int) -> np.ndarray:
        uvw = projections @ np.append(point, 1.0)
        uv = uvw[:, :2] / np.where(uvw[:, 2:] > 1e-9, uvw[:, 2:], np.nan)
        return np.linalg.norm(uv - keypoints[:, k, :2], axis=1)

    n, n_landmarks = keypoints.shape[:2]
    points, support = np.full((n_landmarks, 3), np.nan), np.zeros(n_landmarks, dtype=np.int64)
    for k in range(n_landmarks):
        seen = [v for v in range(n) if keypoints[v, k, 2] > min_visibility]
        best: list[int] = []
        for i, a in enumerate(seen):
            for b in seen[i + 1 :]:
                candidate = solve([a, b], k)
                if not np.isfinite(candidate).all():
                    continue
                inliers = [v for v in seen if errors(candidate, k)[v] < threshold]
                if len(inliers) > len(best):
                    best = inliers
        if len(best) >= 2:
            points[k], support[k] = solve(best, k), len(best)
    return points, support


def fit_anny_to_views(
    cameras: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    masks: list[np.ndarray],
    keypoints: list[np.ndarray],
    steps: int = FIT_STEPS,
) -> dict:
    """Fit Anny to several views of one person in one pose, with known cameras (``K``, ``R``, ``T``:
    ``x_cam = R x + T``): MediaPipe's landmarks (33, 3 per view), triangulated (:func:`triangulate`), and every
    view's person mask (each vertex inside every mask, each mask pixel near some vertex). The body starts upright
    and is placed onto the triangulated torso; returns the fit's parameters (world frame), the body and a report
    (landmark error in 3D, views that agree on each landmark, silhouette IoU is left to the caller)."""
    if not (len(cameras) == len(masks) == len(keypoints)) or len(cameras) < 2:
        raise ValueError("fit_anny_to_views needs at least two views, each with a camera, a mask and keypoints")
    projections = np.stack([K @ np.concatenate([R, np.asarray(T).reshape(3, 1)], 1) for K, R, T in cameras])
    size = float(max(masks[0].shape))
    points, support = triangulate(projections, np.stack(keypoints), threshold=0.02 * size)
    fit = AnnyFit()
    fit.knee_weight = KNEE_WEIGHT_NOT_STANDING  # triangulated landmarks place the knees; no posture is assumed
    model_keypoints = KeypointModel(fit)
    rows = [i for i, k in enumerate(model_keypoints.ids) if support[k] >= 2]
    if len(rows) < 6:
        raise ValueError(f"only {len(rows)} landmarks were found in two or more views; the fit needs six")
    goal = torch.as_tensor(points[[model_keypoints.ids[i] for i in rows]])
    torso_rows = [j for j, i in enumerate(rows) if model_keypoints.ids[i] in TORSO_KEYPOINTS]
    targets = [ImageTargets(K, m, None) for (K, _, _), m in zip(cameras, masks, strict=True)]
    world_to_cam = [(torch.as_tensor(R, dtype=torch.float64), torch.as_tensor(T, dtype=torch.float64).reshape(3))
                    for _, R, T in cameras]  # fmt: skip

    def kp_loss(verts, heads, rots, only=None):
        d = (model_keypoints(verts, heads, rots)[rows] - goal).pow(2).sum(1)
        robust = d / (d + 0.03**2)  # Geman-McClure, 3 cm as scale
        return robust.mean() if only is None else robust[only].mean()

    def silhouette(verts):
        total = torch.zeros((), dtype=torch.float64)
        for t, (R, T) in zip(targets, world_to_cam, strict=True):
            uv = t.project(verts @ R.T + T)
            inside = (t.sample_outside(uv) / t.scale).pow(2).mean()
            cover = torch.cdist(t.mask_pixels, uv[::4]).min(1).values / t.scale
            total = total + inside + cover.pow(2).mean()
        return total / len(targets)

    with torch.no_grad():
        verts, heads, rots = fit()
        start = model_keypoints(verts, heads, rots)[rows].numpy()
    rot, t = procrustes(start[torso_rows], points[[model_keypoints.ids[rows[j]] for j in torso_rows]])
    with torch.no_grad():
        fit.g_rot.copy_(matrix_to_axis_angle(torch.as_tensor(rot)))
        fit.g_t.copy_(torch.as_tensor(t))

    def coarse():
        verts, heads, rots = fit()
        return kp_loss(verts, heads, rots, torso_rows) + 1e-3 * (fit.pheno**2).sum()

    def fine(with_silhouette: bool):
        def loss():
            verts, heads, rots = fit()
            total = kp_loss(verts, heads, rots) + 1e-3 * fit.prior()
            return total + 6.0 * silhouette(verts) if with_silhouette else total

        return loss

    _optimise(fit, [fit.g_rot, fit.g_t, fit.pheno], coarse, 60, 0.05)
    _optimise(fit, list(fit.parameters()), fine(False), steps // 2, 0.02)
    _optimise(fit, list(fit.parameters()), fine(True), steps // 2, 0.01)
    with torch.no_grad():
        verts, heads, rots = fit()
        err = (model_keypoints(verts, heads, rots)[rows] - goal).norm(dim=1).numpy()
    report = {
        "landmark_error_mm": {
            "median": float(np.median(err) * 1000),
            "per_landmark": {int(model_keypoints.ids[i]): float(e * 1000) for i, e in zip(rows, err, strict=True)},
        },
        "views_per_landmark": {int(k): int(support[k]) for k in model_keypoints.ids},
    }
    out = fit.result()
    return {**out, "report": report, "body": AnnyBody(out["phenotype"])}
