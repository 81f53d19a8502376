"""What the fit looks at: the input view, the camera ring, body-prior renders of the training poses, crops.

Poses are indices into the subject's motion. Stage 1 trains on every ``init_frame_step``-th pose,
stage 2 draws its novel poses from every ``train_frame_step``-th (the input pose first in both);
the body prior (template colour, opacity and part labels from every ring camera) is rendered once
for all of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..body import PART_NAMES, PosedBody
from ..body.template import template_colors, vertex_normals
from ..core.cameras import Camera
from ..data.mesh_render import MeshAppearance, MeshRenderer
from ..data.rigs import body_rotation, place_ring
from ..data.subject import Subject, SubjectError
from .completion import facing_cosine, visible_vertices, within_held_reach
from .config import FitConfig
from .hybrid_sampling import body_yaw
from .shading import Shading, estimate_shading, seen_colors

PART_PIXELS_AT = 512 * 512  # ``part_min_pixels`` is counted in an image of this many pixels
CENTRED_PATCH_P = 0.9  # probability that a patch is centred on the person
MIN_INPUT_IOU = 0.1  # below this overlap of body and input mask the subject's pose and camera disagree


def crop_image(image: torch.Tensor, window: tuple[float, float, float], size: int) -> torch.Tensor:
    """Resample the square ``window`` (x0, y0, side) of a (C, H, W) image to (C, size, size); zero outside."""
    c, h, w = image.shape
    x0, y0, side = window
    centres = (torch.arange(size, dtype=torch.float32, device=image.device) + 0.5) * (side / size)
    gx = (x0 + centres) / w * 2 - 1
    gy = (y0 + centres) / h * 2 - 1
    grid = torch.stack(torch.meshgrid(gy, gx, indexing="ij")[::-1], -1)[None]
    return F.grid_sample(image[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0]


def min_part_pixels(part_min_pixels: int, camera: Camera) -> int:
    """The smallest body part worth a crop in ``camera``'s image: ``part_min_pixels`` scaled by image area."""
    return int(part_min_pixels * camera.width * camera.height / PART_PIXELS_AT)


def random_patch(rng: np.random.Generator, mask: np.ndarray, size: int) -> tuple[int, int]:
    """Top-left corner of a size x size patch, centred on the person with probability ``CENTRED_PATCH_P``."""
    h, w = mask.shape
    if rng.random() < CENTRED_PATCH_P and mask.any():
        ys, xs = np.nonzero(mask)
        k = rng.integers(xs.size)
        cx, cy = xs[k], ys[k]
    else:
        cx, cy = rng.integers(w), rng.integers(h)
    return int(np.clip(cx - size // 2, 0, max(0, w - size))), int(np.clip(cy - size // 2, 0, max(0, h - size)))


def training_poses(subject: Subject, step: int, input_only: bool, observed: list[int] | None = None) -> list[int]:
    """The input poses (``observed``, default the first input's), then every ``step``-th pose of the motion (only
    the input poses with ``input_only``)."""
    first = [subject.input_index] if observed is None else observed
    if input_only:
        return list(first)
    return list(first) + [i for i in range(0, len(subject.motion), max(1, step)) if i not in first]


@dataclass
class PriorViews:
    """Body-prior renders of the training poses from every ring camera: part labels of every training pose (stage 2
    crops), template colour and opacity of stage 1's poses only (its targets)."""

    rows: dict[int, int]  # pose -> row of labels and yaws
    labels: np.ndarray  # (P, C, H, W) int8 body parts, -1 background
    yaws: np.ndarray  # (P, C) body-relative yaw of each camera, degrees
    texture_rows: dict[int, int]  # stage 1's poses -> row of color and alpha
    color: np.ndarray  # (T, C, H, W, 3) uint8 template colour
    alpha: np.ndarray  # (T, C, H, W) uint8

    @classmethod
    def render(
        cls, subject: Subject, poses: list[int], textured: list[int], ring: list[Camera], renderer: MeshRenderer
    ) -> PriorViews:
        """Labels of ``poses`` and, for those among ``textured``, colour and opacity (one Mitsuba launch per pose
        and kind of channel)."""
        body = subject.body
        colors, alphas, labels, yaws = [], [], [], []
        for pose in tqdm(poses, desc="body-prior renders", unit="pose", leave=False):
            posed = body.pose(*subject.motion.frame(pose))
            channels = ("color", "alpha", "labels") if pose in textured else ("labels",)
            out = renderer.render(posed.vertices, ring, channels, spp=4)
            if pose in textured:
                colors.append((np.clip(out["color"], 0, 1) * 255 + 0.5).astype(np.uint8))
                alphas.append((out["alpha"] * 255 + 0.5).astype(np.uint8))
            labels.append(out["labels"].astype(np.int8))
            rot = body_rotation(body, posed.bone_transforms)
            yaws.append([body_yaw(c, rot) for c in ring])
        rows = {pose: i for i, pose in enumerate(poses)}
        texture_rows = {pose: i for i, pose in enumerate(p for p in poses if p in textured)}
        size = (len(ring), ring[0].height, ring[0].width)
        color = np.stack(colors) if colors else np.zeros((0, *size, 3), np.uint8)
        alpha = np.stack(alphas) if alphas else np.zeros((0, *size), np.uint8)
        return cls(rows, np.stack(labels), np.array(yaws), texture_rows, color, alpha)


@dataclass
class InputView:
    """An input photo at the working scale, on black, with its mask and the body's part labels."""

    pose: int  # its pose: an index into the subject's motion
    camera: Camera
    image: torch.Tensor  # (3, H, W) on the fit's device
    mask: torch.Tensor  # (H, W) 0/1 float on the fit's device
    person: np.ndarray  # (H, W) bool, the mask on the host (patch sampling)
    labels: np.ndarray  # (H, W) int body part of the posed body, -1 background
    seen: np.ndarray  # (V,) bool: the body vertices the camera sees
    posed: PosedBody  # the body in the photo's pose
    depth: np.ndarray  # (H, W) the posed body's z-depth in ``camera`` (0 = none)
    held: np.ndarray  # (V,) bool: seen vertices within the reach of forearms held in front (no source, no light sample)
    normals: np.ndarray  # (V, 3) the posed body's vertex normals (world)
    shading: Shading  # the photo's light, fitted at full resolution to the seen vertices
    colors: np.ndarray  # (V, 3) the photo's colour at every seen vertex well inside the mask, NaN elsewhere
    facing: np.ndarray  # (V,) cosine between each vertex's normal and the way to the camera
    yaw: float  # the body's facing seen from the camera (:func:`body_yaw`), degrees

    @classmethod
    def load(
        cls, subject: Subject, view: tuple[str, int], scale: float, renderer: MeshRenderer, device: torch.device
    ) -> InputView:
        """The input ``view`` (camera name, frame id) of ``subject``."""
        name, frame = view
        pose = subject.frame_index(frame)
        camera = subject.cameras[name].scaled(scale)
        img = torch.as_tensor(subject.image(name, frame)).permute(2, 0, 1)
        msk = torch.as_tensor(subject.mask(name, frame), dtype=torch.float32)[None]
        size = (camera.height, camera.width)
        mask = (F.interpolate(msk[None], size=size, mode="area")[0, 0] > 0.5).float()
        image = F.interpolate(img[None], size=size, mode="area")[0] * mask
        posed = subject.body.pose(*subject.motion.frame(pose))
        out = renderer.render(posed.vertices, [camera], ("labels", "depth"))
        person = mask.numpy() > 0.5
        normals = vertex_normals(posed.vertices, subject.body.faces)
        seen = visible_vertices(posed.vertices, normals, camera, out["depth"][0], person)
        full = subject.cameras[name]  # the light is fitted to the photo at full resolution
        facing = facing_cosine(posed.vertices, normals, full)
        held = within_held_reach(posed.vertices, subject.body.vertex_parts(), facing, full, seen)
        photo, person_full = img.permute(1, 2, 0).numpy(), msk[0].numpy() > 0.5
        # What the hands may hold (a folder, a bag) is no sample of the light on the body.
        shading = estimate_shading(photo, person_full, full, posed.vertices, normals, seen & ~held)
        colors = np.full(posed.vertices.shape, np.nan)
        idx, rgb = seen_colors(photo, person_full, full, posed.vertices, seen)
        colors[idx] = rgb
        labels = out["labels"][0]
        yaw = body_yaw(full, body_rotation(subject.body, posed.bone_transforms))
        return cls(
            pose,
            camera,
            image.to(device),
            mask.to(device),
            person,
            labels,
            seen,
            posed,
            out["depth"][0],
            held,
            normals,
            shading,
            colors,
            facing,
            yaw,
        )

    def part_colors(self) -> np.ndarray:
        """(P, 3) mean colour of every body part in the image (the whole person's where a part is unseen)."""
        img = self.image.permute(1, 2, 0).cpu().numpy()
        person = self.person & (self.labels >= 0)
        overall = img[person].mean(0) if person.any() else np.full(3, 0.5)
        out = np.tile(overall, (len(PART_NAMES), 1))
        for p in range(len(PART_NAMES)):
            sel = person & (self.labels == p)
            if sel.sum() >= 20:
                out[p] = img[sel].mean(0)
        return out


@dataclass
class FitViews:
    """Everything the fit's losses compare against, built once before training.

    ``observed`` are the input photos the fit reconstructs (every input view of a multi-photo subject; only the
    first with ``multi_photo = "reference"``); ``references`` are the other input photos, which only the semantic
    prior's reference crops read (the paper's use of extra photos)."""

    observed: list[InputView]
    references: list[InputView]
    ring: list[Camera]
    prior: PriorViews
    poses: dict[int, list[int]]  # stage -> its training poses

    @property
    def input(self) -> InputView:
        """The first input photo: the view novel views are measured from."""
        return self.observed[0]

    @classmethod
    def build(cls, subject: Subject, cfg: FitConfig, device: torch.device) -> FitViews:
        body = subject.body
        renderer = MeshRenderer(body.faces, MeshAppearance(vertex_colors=template_colors(body)), body.face_parts())
        views = []
        for name, frame in subject.inputs:
            view = InputView.load(subject, (name, frame), cfg.input_scale, renderer, device)
            covered = view.labels >= 0
            iou = (covered & view.person).sum() / max((covered | view.person).sum(), 1)
            if iou < MIN_INPUT_IOU:
                raise SubjectError(
                    f"{subject.root}: the body in the input pose of view ({name}, frame {frame}) covers {iou:.0%} "
                    f"of the input mask (IoU); check that frame's transl and global_orient in motion.npz against "
                    f"camera {name!r} in cameras.json"
                )
            views.append(view)
        n_observed = len(views) if cfg.multi_photo == "observed" else 1
        observed, references = views[:n_observed], views[n_observed:]
        input_only = cfg.train_poses == "input"
        input_poses = list(dict.fromkeys(v.pose for v in observed))
        poses = {
            1: training_poses(subject, cfg.init_frame_step, input_only, input_poses),
            2: training_poses(subject, cfg.train_frame_step, input_only, input_poses),
        }
        ring = place_ring(subject, cfg.ring_cameras, cfg.label_size)
        needed = list(dict.fromkeys(poses[1] + poses[2]))  # a reference photo's crops read its own labels
        textured = poses[1] if cfg.body_prior else []  # without the body prior no stage 1 reads them
        prior = PriorViews.render(subject, needed, textured, ring, renderer)
        return cls(observed, references, ring, prior, poses)
