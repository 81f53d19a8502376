"""The ELICIT fit: body-render initialisation (stage 1), then one-shot training (stage 2).

Stage 1 trains the avatar to reproduce Mitsuba renders of the template-textured body over the
target motion from a ring of cameras. Stage 2 alternates (p = 0.5) between a patch of the input
image (MSE + perceptual) and a novel (pose, camera) crop chosen by hybrid sampling, supervised by
the semantic loss against a reference crop, the soft silhouette and edge losses against the body
and (not in the paper) a binary-entropy prior on the crop's opacity.

A run folder holds ``checkpoint.pt`` (resumable), ``avatar.pt`` (the result), ``run.json``,
``log.txt`` and ``previews/``.
"""

from __future__ import annotations

import logging
import pickle
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from .avatar import Avatar
from .body.template import template_colors
from .cameras import Camera
from .config import FitConfig, config_dict
from .device import default_device
from .encoders import load_encoder
from .errors import ElicitError
from .io import atomic_write, write_image, write_json
from .losses import Perceptual, edge_distance, edge_loss, mse, opacity_entropy, semantic_loss, silhouette_loss
from .mesh_render import MeshAppearance, MeshRenderer
from .rigs import place_cameras, read_rig, shipped_rig_path
from .sampling import body_yaw, crop_window, part_pixels, plan_novel_view
from .subject import Subject

log = logging.getLogger("elicit.fit")
RING_SIZE = 512  # image size of the shipped ring rig


class FitError(ElicitError):
    """A fit that cannot start or continue."""


def crop_image(image: torch.Tensor, window: tuple[float, float, float], size: int) -> torch.Tensor:
    """Resample the square ``window`` (x0, y0, side) of a (C, H, W) image to (C, size, size); zero outside."""
    c, h, w = image.shape
    x0, y0, side = window
    centres = (torch.arange(size, dtype=torch.float32, device=image.device) + 0.5) * (side / size)
    gx = (x0 + centres) / w * 2 - 1
    gy = (y0 + centres) / h * 2 - 1
    grid = torch.stack(torch.meshgrid(gy, gx, indexing="ij")[::-1], -1)[None]
    return F.grid_sample(image[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0]


def place_ring(subject: Subject, n: int, size: int) -> list[Camera]:
    """The shipped ring, centred on the input pose's pelvis, upright for the input camera, facing the body."""
    body = subject.body
    posed = body.pose(*subject.motion.frame(subject.input_index))
    pelvis = body.joint_index(body.semantic["pelvis"])
    rest = body.pose(body.zero_pose()).bone_transforms[pelvis, :3, :3]
    rot_body = posed.bone_transforms[pelvis, :3, :3] @ rest.T
    up = -subject.cameras[subject.input_camera].R[1]
    facing = rot_body[:, 2] - (rot_body[:, 2] @ up) * up
    facing /= np.linalg.norm(facing)
    place = np.stack([np.cross(up, facing), up, facing], axis=1)
    cams = read_rig(shipped_rig_path("ring"))
    if n != len(cams):
        from .rigs import ring_cameras

        cams = ring_cameras(n=n)
    return [c.scaled(size / RING_SIZE) for c in place_cameras(cams, place, posed.bone_transforms[pelvis, :3, 3])]


@dataclass
class PriorViews:
    """Body-prior renders of the training frames from the ring (stage 1 targets, stage 2 crops)."""

    frames: list[int]  # motion frame indices
    cameras: list[Camera]
    color: np.ndarray  # (F, C, H, W, 3) uint8 template colour
    alpha: np.ndarray  # (F, C, H, W) uint8
    labels: np.ndarray  # (F, C, H, W) int8 body parts, -1 background
    yaws: np.ndarray  # (F, C) body-relative yaw, degrees


@dataclass
class RunStats:
    stage_seconds: dict = field(default_factory=dict)
    recoveries: list = field(default_factory=list)
    losses: dict = field(default_factory=dict)
    skipped_semantic: int = 0


class Fitter:
    def __init__(self, subject: Subject, cfg: FitConfig, run_dir: str | Path) -> None:
        self.subject, self.cfg = subject, cfg
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.rng = np.random.default_rng(cfg.seed)
        torch.manual_seed(cfg.seed)
        self.stats = RunStats()
        self._spaces: dict = {}
        self.step = 0
        self.stage = 1
        self.lr_scale = 1.0
        self.body = subject.body
        self.device = default_device()
        ab = cfg.ablation
        self.hybrid = ab != "no_hybrid_sampling"
        self.soft_silhouette = ab != "hard_silhouette"
        self.w_semantic = 0.0 if ab == "no_semantic" else cfg.w_semantic
        self.w_sil = 0.0 if ab == "no_silhouette" else cfg.w_silhouette
        self.w_edge = 0.0 if ab == "no_silhouette" else cfg.w_edge
        self.use_init = ab != "no_init"

    # ---- set-up -------------------------------------------------------------------------------------
    def training_frames(self) -> list[int]:
        motion, k = self.subject.motion, max(1, self.cfg.train_frame_step)
        idx = self.subject.input_index
        if self.cfg.ablation == "input_pose_only":
            return [idx]
        return [idx] + [i for i in range(0, len(motion), k) if i != idx]

    def prepare(self) -> None:
        cfg, subject = self.cfg, self.subject
        t0 = time.perf_counter()
        self.avatar = Avatar.from_body(
            self.body,
            subject.body_spec,
            cfg.voxel_size,
            cfg.box_margin,
            cfg.density_activation,
            cfg.occupancy_cell,
            cfg.weight_grid,
            config_dict(cfg),
            body_prior=self.use_init,
        )
        self.avatar.to(self.device)
        self.avatar.motion_weights.logits.requires_grad_(cfg.learn_motion_weights)
        self.avatar.pose_delta.requires_grad_(cfg.refine_input_pose)
        self.outside_body = self.outside_body_mask()
        self.frames = self.training_frames()
        self.pose_frames = {f: self.avatar.pose_frames(*subject.motion.frame(f)) for f in self.frames}
        self.ring = place_ring(subject, cfg.ring_cameras, cfg.label_size)
        self.prior = self.render_prior()
        # The input view at the working scale, on black, with its body-part labels.
        cam = subject.cameras[subject.input_camera]
        self.input_cam = cam.scaled(cfg.input_scale)
        img = torch.as_tensor(subject.image(subject.input_camera, subject.input_frame)).permute(2, 0, 1)
        msk = torch.as_tensor(subject.mask(subject.input_camera, subject.input_frame), dtype=torch.float32)[None]
        size = (self.input_cam.height, self.input_cam.width)
        self.input_image = F.interpolate(img[None], size=size, mode="area")[0].to(self.device)
        self.input_mask = (F.interpolate(msk[None], size=size, mode="area")[0, 0] > 0.5).float().to(self.device)
        self.input_image = self.input_image * self.input_mask
        renderer = self.prior_renderer()
        posed = self.body.pose(*subject.motion.frame(subject.input_index))
        self.input_labels = renderer.render(posed.vertices, [self.input_cam], ("labels",))["labels"][0]
        # The semantic encoder and the perceptual term: say which ones are in use.
        self.encoder, self.encoder_info = (
            load_encoder(cfg.encoder, cfg.clip_model, cfg.clip_pretrained)
            if self.w_semantic > 0 or cfg.w_text > 0
            else (None, None)
        )
        if self.encoder is not None:
            self.encoder.to(self.device)
        self.perceptual = Perceptual(cfg.perceptual, self.device)
        self.text_embedding = None
        if cfg.text_prompt and cfg.w_text > 0 and self.encoder is not None:
            self.text_embedding = self.encoder.encode_text(cfg.text_prompt)
        self.make_optimizer(cfg.init_lr if self.use_init else cfg.lr)
        self.stats.stage_seconds["prepare"] = time.perf_counter() - t0
        log.info(
            "semantic encoder: %s%s",
            self.encoder_info.name if self.encoder_info else "none (disabled)",
            f" [{self.encoder_info.reason}]" if self.encoder_info and self.encoder_info.reason else "",
        )
        log.info(
            "perceptual term: %s%s",
            self.perceptual.name,
            f" [{self.perceptual.reason}]" if self.perceptual.reason else "",
        )

    def outside_body_mask(self) -> torch.Tensor:
        """1 for grid cells more than one cell outside the canonical body (where density is clothing)."""
        from .body.template import vertex_normals
        from .field import grid_points, signed_distance

        canon = self.body.pose(self.body.canonical_pose())
        field = self.avatar.field
        pts = grid_points(field.box.double(), field.shape).reshape(-1, 3).numpy()
        sdf = signed_distance(pts, canon.vertices, vertex_normals(canon.vertices, self.body.faces))
        return torch.as_tensor((sdf > field.voxel_size).reshape(field.shape), dtype=torch.float32, device=self.device)

    def prior_renderer(self) -> MeshRenderer:
        if not hasattr(self, "_prior_renderer"):
            self._prior_renderer = MeshRenderer(
                self.body.faces, MeshAppearance(vertex_colors=template_colors(self.body)), self.body.face_parts()
            )
        return self._prior_renderer

    def render_prior(self) -> PriorViews:
        renderer = self.prior_renderer()
        body = self.body
        pelvis = body.joint_index(body.semantic["pelvis"])
        rest = body.pose(body.zero_pose()).bone_transforms[pelvis, :3, :3]
        colors, alphas, labels, yaws = [], [], [], []
        for f in tqdm(self.frames, desc="body-prior renders", unit="frame", leave=False):
            posed = body.pose(*self.subject.motion.frame(f))
            out = renderer.render(posed.vertices, self.ring, ("color", "alpha", "labels"), spp=4)
            colors.append((np.clip(out["color"], 0, 1) * 255 + 0.5).astype(np.uint8))
            alphas.append((out["alpha"] * 255 + 0.5).astype(np.uint8))
            labels.append(out["labels"].astype(np.int8))
            rot = posed.bone_transforms[pelvis, :3, :3] @ rest.T
            yaws.append([body_yaw(c, rot) for c in self.ring])
        return PriorViews(self.frames, self.ring, np.stack(colors), np.stack(alphas), np.stack(labels), np.array(yaws))

    def make_optimizer(self, lr: float) -> None:
        f = self.avatar.field
        density_lr = lr * (self.cfg.stage2_density_lr if self.stage == 2 else 1.0)
        groups = [
            {"params": [f.density], "lr": density_lr, "base_lr": density_lr},
            {"params": [f.color], "lr": lr, "base_lr": lr},
        ]
        if self.cfg.learn_motion_weights:
            groups.append(
                {
                    "params": [self.avatar.motion_weights.logits],
                    "lr": self.cfg.motion_weights_lr,
                    "base_lr": self.cfg.motion_weights_lr,
                }
            )
        if self.cfg.refine_input_pose:
            groups.append({"params": [self.avatar.pose_delta], "lr": 1e-3, "base_lr": 1e-3})
        self.opt = torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-8)

    def set_lr(self, progress: float) -> None:
        decay = self.cfg.lr_decay**progress if self.stage == 2 else 1.0
        for g in self.opt.param_groups:
            g["lr"] = g["base_lr"] * decay * self.lr_scale

    def input_part_colors(self) -> np.ndarray:
        """(P, 3) mean colour of every body part in the input image (the whole person's where unseen)."""
        from .body import PART_NAMES

        img = self.input_image.permute(1, 2, 0).cpu().numpy()
        person = (self.input_mask.cpu().numpy() > 0.5) & (self.input_labels >= 0)
        overall = img[person].mean(0) if person.any() else np.full(3, 0.5)
        out = np.tile(overall, (len(PART_NAMES), 1))
        for p in range(len(PART_NAMES)):
            sel = person & (self.input_labels == p)
            if sel.sum() >= 20:
                out[p] = img[sel].mean(0)
        return out

    def colors_from_input(self) -> None:
        canon = self.body.pose(self.body.canonical_pose())
        self.avatar.field.set_colors_by_part(canon.vertices, self.body.vertex_parts(), self.input_part_colors())
        log.info("stage 2 colours: reset to the input image's mean colour per body part")

    def tensor(self, array) -> torch.Tensor:
        """A float32 tensor on the fit's device."""
        return torch.as_tensor(np.asarray(array, dtype=np.float32), device=self.device)

    # ---- rendering helpers ---------------------------------------------------------------------------
    def frames_for(self, f: int) -> torch.Tensor:
        frames = self.pose_frames[f]
        if self.cfg.refine_input_pose and f == self.subject.input_index:
            return self.avatar.refined(frames)
        return frames

    def space(self, f: int) -> tuple:
        """Observation-space box and occupancy of a training frame, cached; refreshed every 50 steps
        when the motion weights or the input pose are being learned."""
        moving = self.cfg.learn_motion_weights or (self.cfg.refine_input_pose and f == self.subject.input_index)
        key = self.step // 50 if moving else -1
        cached = self._spaces.get(f)
        if cached is None or cached[0] != key:
            cached = (key, self.avatar.observation_space(self.frames_for(f).detach()))
            self._spaces[f] = cached
        return cached[1]

    def render(
        self, camera: Camera, f: int, background: torch.Tensor, outputs=("rgb", "alpha"), grad: bool = True
    ) -> dict:
        origins, dirs = camera.rays(device=self.device)
        with torch.set_grad_enabled(grad):
            out = self.avatar.render_rays(
                origins,
                dirs,
                self.frames_for(f),
                self.cfg.samples_per_ray,
                background,
                jitter=grad,
                seed=int(self.rng.integers(1 << 30)),
                outputs=outputs,
                t_thresh=self.cfg.t_thresh,
                space=self.space(f),
            )
        h, w = camera.height, camera.width
        res = {"alpha": out["alpha"].reshape(1, h, w)}
        if "rgb" in out:
            res["rgb"] = out["rgb"].reshape(h, w, 3).permute(2, 0, 1)[None]
        return res

    def random_patch(self, mask: np.ndarray, size: int) -> tuple[int, int]:
        """Top-left corner of a size x size patch, centred on the person with probability 0.9."""
        h, w = mask.shape
        if self.rng.random() < 0.9 and mask.any():
            ys, xs = np.nonzero(mask)
            k = self.rng.integers(xs.size)
            cx, cy = xs[k], ys[k]
        else:
            cx, cy = self.rng.integers(w), self.rng.integers(h)
        return int(np.clip(cx - size // 2, 0, max(0, w - size))), int(np.clip(cy - size // 2, 0, max(0, h - size)))

    def recon_loss(self, render: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, dict]:
        per = self.perceptual(render, target)
        err = mse(render, target)
        terms = {"perc": float(per.detach()), "mse": float(err.detach())}
        return self.cfg.w_perceptual * per + self.cfg.w_mse * err, terms

    # ---- steps ------------------------------------------------------------------------------------------
    def stage1_step(self) -> tuple[torch.Tensor, dict]:
        """Reconstruct a patch of a template-textured body render (random background)."""
        fi = int(self.rng.integers(len(self.frames)))
        ci = int(self.rng.integers(len(self.ring)))
        size = min(self.cfg.crop_size, self.cfg.label_size)
        alpha = self.prior.alpha[fi, ci].astype(np.float32) / 255.0
        x0, y0 = self.random_patch(alpha > 0.5, size)
        cam = self.ring[ci].crop(x0, y0, size, size, size)
        bg = torch.rand(3, device=self.device)
        out = self.render(cam, self.frames[fi], bg)
        color = self.tensor(self.prior.color[fi, ci, y0 : y0 + size, x0 : x0 + size]) / 255.0
        a = self.tensor(alpha[y0 : y0 + size, x0 : x0 + size])
        target = (color * a[..., None] + bg * (1 - a[..., None])).permute(2, 0, 1)[None]
        loss, terms = self.recon_loss(out["rgb"], target)
        sil = mse(out["alpha"][0], a)
        return loss + sil, {**terms, "alpha": float(sil.detach())}

    def input_step(self) -> tuple[torch.Tensor, dict]:
        """Reconstruct a patch of the input image (random background)."""
        size = min(self.cfg.crop_size, self.input_cam.width, self.input_cam.height)
        x0, y0 = self.random_patch(self.input_mask.cpu().numpy() > 0.5, size)
        cam = self.input_cam.crop(x0, y0, size, size, size)
        bg = torch.rand(3, device=self.device)
        out = self.render(cam, self.subject.input_index, bg)
        m = self.input_mask[y0 : y0 + size, x0 : x0 + size]
        target = self.input_image[:, y0 : y0 + size, x0 : x0 + size] * m + bg[:, None, None] * (1 - m)
        loss, terms = self.recon_loss(out["rgb"], target[None])
        return loss, terms

    def novel_step(self) -> tuple[torch.Tensor, dict] | None:
        """A hybrid-sampled novel (pose, camera) crop: semantic, soft silhouette, edge and opacity losses."""
        cfg = self.cfg
        fi = int(self.rng.integers(len(self.frames)))
        labels = list(self.prior.labels[fi].astype(np.int16))
        min_px = int(cfg.part_min_pixels * (cfg.label_size / 512.0) ** 2)
        view = plan_novel_view(self.rng, self.prior.yaws[fi], labels, fi, min_px, self.hybrid)
        if view is None:
            return None
        size = cfg.crop_size
        cam = self.ring[view.camera].crop(*view.window[:2], view.window[2], view.window[2], size)
        black = torch.zeros(3, device=self.device)
        out = self.render(cam, self.frames[fi], black)
        body = self.tensor(labels[view.camera] >= 0)[None]
        mask = crop_image(body, view.window, size)[0].clamp(0, 1)
        terms: dict = {"part": view.part}
        loss = torch.zeros((), device=self.device)
        if self.w_sil > 0:
            sil = silhouette_loss(out["alpha"][0], mask, soft=self.soft_silhouette)
            loss = loss + self.w_sil * sil
            terms["sil"] = float(sil.detach())
        if self.w_edge > 0:
            dist = self.tensor(edge_distance(mask.cpu().numpy() > 0.5))
            e = edge_loss(out["alpha"], mask[None], dist[None])
            loss = loss + self.w_edge * e
            terms["edge"] = float(e.detach())
        if cfg.w_opacity > 0:
            ent = opacity_entropy(out["alpha"])
            loss = loss + cfg.w_opacity * ent
            terms["opacity"] = float(ent.detach())
        if self.encoder is not None and (self.w_semantic > 0 or self.text_embedding is not None):
            ref = self.reference(view, fi)
            if ref is None:
                self.stats.skipped_semantic += 1
            else:
                ref_img, ref_mask = ref
                part = crop_image(
                    self.tensor(part_pixels(labels[view.camera], view.part))[None],
                    view.window,
                    size,
                )
                emb = self.encoder(torch.cat([ref_img, out["rgb"]]), torch.cat([ref_mask, part]))
                if self.w_semantic > 0:
                    sem = semantic_loss(emb[:1].detach(), emb[1:])
                    loss = loss + self.w_semantic * sem
                    terms["sem"] = float(sem.detach())
                if self.text_embedding is not None:
                    txt = semantic_loss(self.text_embedding[None], emb[1:])
                    loss = loss + cfg.w_text * txt
                    terms["text"] = float(txt.detach())
        return loss, terms

    def reference(self, view, fi: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The semantic reference crop and its part mask: the input image's matching crop, or a
        no-grad render from the nearest side (rear views) or front (side views of the head) camera."""
        size = self.cfg.crop_size
        if view.reference == "render":
            mask = part_pixels(self.prior.labels[fi, view.ref_camera].astype(np.int16), view.part)
            window = crop_window(mask, view.part)
            if window is None:
                return None
            cam = self.ring[view.ref_camera].crop(*window[:2], window[2], window[2], size)
            image = self.render(cam, self.frames[fi], torch.zeros(3, device=self.device), grad=False)["rgb"].detach()
        else:
            mask = part_pixels(self.input_labels.astype(np.int16), view.part)
            if mask.sum() < self.cfg.part_min_pixels * (self.input_cam.width / 512.0) ** 2 / 4:
                return None
            window = crop_window(mask, view.part)
            image = crop_image(self.input_image, window, size)[None]
        return image, crop_image(self.tensor(mask)[None], window, size)

    # ---- checkpoints, previews, guards ------------------------------------------------------------------
    def checkpoint_path(self) -> Path:
        return self.run_dir / "checkpoint.pt"

    def save_checkpoint(self) -> None:
        data = {
            "avatar": self.avatar.state(),
            "optimizer": self.opt.state_dict(),
            "step": self.step,
            "stage": self.stage,
            "lr_scale": self.lr_scale,
            "rng": self.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "stats": self.stats.__dict__,
        }
        atomic_write(self.checkpoint_path(), lambda p: torch.save(data, p))

    def load_checkpoint(self) -> bool:
        path = self.checkpoint_path()
        if not path.is_file():
            return False
        try:
            data = torch.load(path, map_location="cpu", weights_only=False)
            self.avatar.load_state_dict(data["avatar"]["tensors"])
            self.stage, self.step, self.lr_scale = data["stage"], data["step"], data["lr_scale"]
            self.make_optimizer(self.cfg.lr if self.stage == 2 else self.cfg.init_lr)
            self.opt.load_state_dict(data["optimizer"])  # fails on another version's parameter groups
            self.rng.bit_generator.state = data["rng"]
            torch.set_rng_state(data["torch_rng"])
            self.stats.__dict__.update(data["stats"])
        except (OSError, EOFError, KeyError, TypeError, ValueError, RuntimeError, pickle.UnpicklingError) as exc:
            raise FitError(
                f"{path}: cannot resume from this checkpoint ({type(exc).__name__}: {exc}); "
                "delete it, or fit without --resume"
            ) from exc
        log.info("resumed from %s at stage %d step %d", path, self.stage, self.step)
        return True

    def snapshot(self, coverage: float | None = None) -> dict:
        """A copy of the avatar's tensors: the guard's last good state, whose input coverage it keeps."""
        self.good_coverage = self.input_coverage() if coverage is None else coverage
        return {k: v.detach().clone() for k, v in self.avatar.state_dict().items()}

    @torch.no_grad()
    def input_coverage(self, size: int = 96) -> float:
        """Mean rendered alpha inside the input mask, at low resolution (the empty-render check)."""
        cam = self.input_cam.scaled(size / max(self.input_cam.width, self.input_cam.height))
        black = torch.zeros(3, device=self.device)
        alpha = self.render(cam, self.subject.input_index, black, ("alpha",), grad=False)["alpha"][0]
        mask = F.interpolate(self.input_mask[None, None], size=alpha.shape, mode="area")[0, 0] > 0.5
        return float(alpha[mask].mean()) if mask.any() else 1.0

    def guard(self, good: dict) -> dict:
        """Detect an emptied (or NaN) avatar, whose input coverage fell below 0.2 and below half the last
        good state's (an avatar that starts empty, as without the body prior, may grow): restore the
        last good state and halve the learning rate."""
        coverage = self.input_coverage()
        finite = all(torch.isfinite(v).all() for v in self.avatar.state_dict().values() if v.is_floating_point())
        if finite and coverage >= min(0.2, 0.5 * self.good_coverage):
            return self.snapshot(coverage)
        self.avatar.load_state_dict(good)
        self.lr_scale *= 0.5
        event = {
            "step": self.step,
            "stage": self.stage,
            "coverage": coverage,
            "finite": finite,
            "lr_scale": self.lr_scale,
        }
        self.stats.recoveries.append(event)
        log.warning(
            "empty render detected at stage %d step %d (input coverage %.3f, finite %s): restored the "
            "last good state, learning rate x%.3g",
            self.stage,
            self.step,
            coverage,
            finite,
            self.lr_scale,
        )
        self.make_optimizer(self.cfg.lr if self.stage == 2 else self.cfg.init_lr)
        return good

    @torch.no_grad()
    def preview(self, tag: str) -> Path:
        """Input view (target | render) and three novel views of the input pose and a mid-motion pose."""
        size = 160
        cams = [self.input_cam.scaled(size / max(self.input_cam.width, self.input_cam.height))]
        ring = [self.ring[round(k * len(self.ring) / 4)] for k in (1, 2, 3)]
        cams += [c.scaled(size / c.width) for c in ring]
        target = F.interpolate(self.input_image[None], size=(cams[0].height, cams[0].width), mode="area")[0]
        tiles = [target.permute(1, 2, 0).cpu().numpy()]
        frames = [self.subject.input_index, self.frames[len(self.frames) // 2]]
        for f in frames:
            for cam in cams:
                tiles.append(self.avatar.render_image(cam, self.frames_for(f), self.cfg.samples_per_ray)["rgb"])
        h = max(t.shape[0] for t in tiles)
        tiles = [np.pad(t, ((0, h - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
        return write_image(self.run_dir / "previews" / f"{tag}.png", np.concatenate(tiles, 1))

    # ---- the loop -----------------------------------------------------------------------------------------
    def run_stage(self, stage: int, steps: int) -> None:
        cfg = self.cfg
        if self.stage > stage or steps <= 0:
            return
        if self.stage < stage:
            self.stage, self.step = stage, 0
            if stage == 2 and cfg.stage2_color == "part_mean":
                self.colors_from_input()
            self.make_optimizer(cfg.lr)
        start = time.perf_counter()
        good = self.snapshot()
        smooth: dict[str, float] = {}
        bar = tqdm(total=steps, initial=self.step, desc=f"stage {stage}", unit="step", dynamic_ncols=True)
        while self.step < steps:
            self.set_lr(self.step / max(1, steps))
            if stage == 1:
                result = self.stage1_step()
            elif self.rng.random() < cfg.p_novel:
                result = self.novel_step()
            else:
                result = self.input_step()
            if result is None:
                continue
            loss, terms = result
            block = self.avatar.field.random_block()
            if cfg.w_tv > 0:
                loss = loss + cfg.w_tv * self.avatar.field.tv_loss(block)
            if stage == 2 and cfg.w_sparsity > 0:
                loss = loss + cfg.w_sparsity * self.avatar.field.sparsity_loss(block, self.outside_body)
            self.opt.zero_grad(set_to_none=True)
            if not torch.isfinite(loss):
                good = self.guard(good)
                continue
            loss.backward()
            self.opt.step()
            self.step += 1
            for k, v in terms.items():
                if isinstance(v, float):
                    smooth[k] = v if k not in smooth else 0.95 * smooth[k] + 0.05 * v
            bar.update(1)
            bar.set_postfix({k: f"{v:.3g}" for k, v in smooth.items()}, refresh=False)
            if self.step % cfg.preview_every == 0 or self.step == steps:
                good = self.guard(good)
                self.preview(f"stage{stage}_{self.step:06d}")
            if self.step % cfg.checkpoint_every == 0 or self.step == steps:
                self.save_checkpoint()
        bar.close()
        self.stats.losses[f"stage{stage}"] = smooth
        key = f"stage{stage}"
        self.stats.stage_seconds[key] = self.stats.stage_seconds.get(key, 0.0) + time.perf_counter() - start

    def run(self, resume: bool = False) -> dict:
        t0 = time.perf_counter()
        self.prepare()
        if resume:
            self.load_checkpoint()
        elif self.checkpoint_path().exists():
            raise FitError(
                f"{self.run_dir} already holds a checkpoint: pass --resume to continue it, or use a new --out"
            )
        if self.use_init:
            self.run_stage(1, self.cfg.init_steps)
        self.run_stage(2, self.cfg.steps)
        avatar_path = self.avatar.save(self.run_dir / "avatar.pt")
        self.stats.stage_seconds["total"] = time.perf_counter() - t0
        report = {
            "subject": str(self.subject.root),
            "avatar": str(avatar_path),
            "config": config_dict(self.cfg),
            "encoder": self.encoder_info.to_dict() if self.encoder_info else None,
            "perceptual": {"name": self.perceptual.name, "reason": self.perceptual.reason},
            "training_frames": self.frames,
            "ring_cameras": len(self.ring),
            "seconds": self.stats.stage_seconds,
            "recoveries": self.stats.recoveries,
            "final_losses": self.stats.losses,
            "semantic_references_skipped": self.stats.skipped_semantic,
            "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "device": str(self.device),
            "torch_threads": torch.get_num_threads(),
        }
        write_json(self.run_dir / "run.json", report)
        return report


def setup_logging(run_dir: Path) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(run_dir / "log.txt")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger("elicit")
    root.setLevel(logging.INFO)
    root.handlers = [handler, logging.StreamHandler()]


def fit(subject: Subject, cfg: FitConfig, run_dir: str | Path, resume: bool = False) -> dict:
    """Fit an avatar to ``subject`` (or the baseline that ``cfg.baseline`` names); returns the run report
    (also written to ``run_dir/run.json``)."""
    setup_logging(Path(run_dir))
    if cfg.baseline == "explicit_texture":
        return fit_explicit_texture(subject, cfg, Path(run_dir))
    return Fitter(subject, cfg, run_dir).run(resume)


def fit_explicit_texture(subject: Subject, cfg: FitConfig, run_dir: Path) -> dict:
    """The body mesh with a per-vertex texture fitted to the input view only (the paper's baseline)."""
    from .baseline import TexturedBody

    t0 = time.perf_counter()
    path = TexturedBody.fit(subject).save(run_dir / "avatar.pt")
    log.info("baseline explicit_texture: per-vertex colours from the input view")
    report = {
        "subject": str(subject.root),
        "avatar": str(path),
        "config": config_dict(cfg),
        "encoder": None,
        "perceptual": {"name": "none (closed-form fit)", "reason": ""},
        "seconds": {"total": time.perf_counter() - t0},
        "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    write_json(run_dir / "run.json", report)
    return report
