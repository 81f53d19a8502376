"""The training loop: optimiser groups, schedules, the two stages, checkpoints, guard and previews."""

from __future__ import annotations

import logging
import resource
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..core.device import default_device
from ..core.io import write_image, write_json
from ..data.subject import Subject
from ..model.avatar import AVATAR_FILE, Avatar
from ..model.field import grid_points
from .checkpoint import CHECKPOINT, FitError, load_optimizer_state, optimizer_state, read_checkpoint, save_checkpoint
from .config import FitConfig, config_dict
from .guard import EmptyRenderGuard
from .objective import Objective, Terms
from .render import PoseRenderer
from .room import input_room
from .streams import RandomStreams
from .views import FitViews

log = logging.getLogger("elicit.fit")
ADAM = {"betas": (0.9, 0.99), "eps": 1e-8, "fused": True}  # fused: one pass over each grid per step
PREVIEW_SIZE = 160
NONFINITE = "nonfinite steps"  # the LossMeter's count of steps whose loss was not finite
PROGRESS_FILE = "progress.json"  # the stage and step last logged, for a page or tool that watches the fit


@dataclass
class RunStats:
    seconds: dict[str, float] = field(default_factory=dict)  # per phase, summed over resumed runs
    recoveries: list[dict] = field(default_factory=list)  # guard events
    losses: dict[str, dict[str, float]] = field(default_factory=dict)  # per stage, the last read-out


def _named(name: str, reason: str) -> str:
    return f"{name} [{reason}]" if reason else name


class LossMeter:
    """Sums each term's detached value on the device and reads the means out every ``every`` steps, so
    that a step never waits for the device just to log. Steps whose loss was not finite are left out of the
    means and counted (``NONFINITE`` in the read-out)."""

    def __init__(self, every: int) -> None:
        self.every, self.sums, self.count = every, {}, 0

    def add(self, terms: Terms, skipped: torch.Tensor) -> dict[str, float] | None:
        """Add one step's terms (``skipped``: a bool tensor, its loss was not finite); every ``every`` steps, the
        means since the last read-out."""
        for name, value in terms.items():
            self.sums[name] = self.sums.get(name, 0.0) + torch.where(skipped, 0.0, value.detach())
        self.sums[NONFINITE] = self.sums.get(NONFINITE, 0.0) + skipped.float()
        self.count += 1
        return self.read() if self.count >= self.every else None

    def read(self) -> dict[str, float] | None:
        """The means since the last read-out (one host read), and the count of non-finite steps."""
        if self.count == 0:
            return None
        names = list(self.sums)
        values = torch.stack([torch.as_tensor(self.sums[n], dtype=torch.float64) for n in names]).tolist()
        totals = dict(zip(names, values, strict=True))
        bad = totals.pop(NONFINITE)
        means = {name: total / max(self.count - bad, 1.0) for name, total in totals.items()}
        self.sums, self.count = {}, 0
        return {**means, NONFINITE: bad}


class Trainer:
    """ELICIT's two-stage optimisation of one avatar; ``run`` writes the avatar file and ``run.json``."""

    def __init__(self, subject: Subject, cfg: FitConfig, run_dir: str | Path) -> None:
        t0 = time.perf_counter()
        self.subject, self.cfg, self.run_dir = subject, cfg, Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.device = default_device()
        self.streams = RandomStreams.from_seed(cfg.seed)
        torch.manual_seed(cfg.seed)
        self.stats = RunStats()
        self.stage, self.step, self.lr_scale = 1, 0, 1.0
        body = subject.body
        self.room = input_room(subject, cfg.box_margin, cfg.garment_hull, cfg.hair_hull)
        if self.room.extends is not None:
            log.info(
                "room: the input mask reaches %.2f m from the body (box_margin %.2f m)", self.room.reach, cfg.box_margin
            )
        if self.room.hull is not None:
            log.info("room: hulls of %s reach %.2f m", " and ".join(self.room.hull_names), self.room.hull_reach)
        self.avatar = Avatar.from_body(
            body,
            subject.body_spec,
            cfg.voxel_size,
            self.room,
            cfg.density_activation,
            cfg.occupancy_cell,
            cfg.weight_grid,
            config_dict(cfg),
            body_prior=cfg.body_prior,
        ).to(self.device)
        self.avatar.motion_weights.logits.requires_grad_(cfg.learn_motion_weights)
        self.avatar.pose_delta.requires_grad_(cfg.refine_input_pose)
        self.views = FitViews.build(subject, cfg, self.device)
        if cfg.refine_input_pose:
            self.avatar.set_refined_poses([subject.motion.frame(v.pose) for v in self.views.observed])
        if len(subject.inputs) > 1:
            log.info(
                "input photos: %d observed, %d semantic references only (multi_photo=%s)",
                len(self.views.observed),
                len(self.views.references),
                cfg.multi_photo,
            )
        poses = list(self.views.prior.rows)
        self.renderer = PoseRenderer(
            self.avatar, subject, poses, cfg.samples_per_ray, cfg.t_thresh, self.streams, cfg.warp_cell
        )
        self.hull = None  # flat bool over the grid's cells: the room's hulls (hair, a garment between the legs)
        if self.room.hull is not None:
            f = self.avatar.field
            self.hull = self.room.hull(grid_points(f.box.double().cpu(), f.shape).reshape(-1, 3).numpy())
        self.objective = Objective(cfg, self.views, self.renderer, self.streams, body, self.avatar.body_sdf, self.hull)
        self.guard = EmptyRenderGuard(self.avatar, self.renderer, self.views.input)
        self.make_optimizer()
        self.stats.seconds["prepare"] = time.perf_counter() - t0
        info, perceptual = self.objective.encoder_info, self.objective.perceptual
        log.info("semantic encoder: %s", _named(info.name, info.reason) if info else "none (disabled)")
        log.info("perceptual term: %s", _named(perceptual.name, perceptual.reason))

    # ---- optimiser --------------------------------------------------------------------------------------
    def make_optimizer(self) -> None:
        """Adam over density, colour and (if learned) the motion weights and the input-pose correction,
        at the current stage's learning rates (before the schedule and the guard's scale)."""
        cfg, f = self.cfg, self.avatar.field
        lr = cfg.init_lr if self.stage == 1 and cfg.body_prior else cfg.lr
        density_lr = lr * (cfg.stage2_density_lr if self.stage == 2 else 1.0)
        groups = [(f.density, density_lr), (f.color, lr)]
        if cfg.learn_motion_weights:
            groups.append((self.avatar.motion_weights.logits, cfg.motion_weights_lr))
        if cfg.refine_input_pose:
            groups.append((self.avatar.pose_delta, cfg.pose_lr))
        self.opt = torch.optim.Adam([{"params": [p], "lr": r, "base_lr": r} for p, r in groups], **ADAM)

    def set_lr(self, progress: float) -> None:
        """Exponential decay over stage 2 (``lr_decay`` in all), times the guard's scale."""
        decay = self.cfg.lr_decay**progress if self.stage == 2 else 1.0
        for g in self.opt.param_groups:
            g["lr"] = g["base_lr"] * decay * self.lr_scale

    # ---- checkpoints ------------------------------------------------------------------------------------
    def save(self) -> None:
        state = {
            "avatar": dict(self.avatar.state_dict()),
            "optimizer": optimizer_state(self.opt),
            "step": self.step,
            "stage": self.stage,
            "lr_scale": self.lr_scale,
            "streams": self.streams.state(),
            "stats": asdict(self.stats),
            "skipped_references": self.objective.skipped_references,
            "completion": self.objective.completion.state() if self.objective.completion is not None else {},
        }
        save_checkpoint(self.run_dir, state)

    def resume(self) -> None:
        path = self.run_dir / CHECKPOINT
        state = read_checkpoint(self.run_dir)
        try:
            self.avatar.load_state_dict(state["avatar"])
            self.stage, self.step, self.lr_scale = int(state["stage"]), int(state["step"]), float(state["lr_scale"])
            self.make_optimizer()
            load_optimizer_state(self.opt, state["optimizer"])
            self.streams.load_state(state["streams"])
            self.stats = RunStats(**state["stats"])
            self.objective.skipped_references = int(state["skipped_references"])
            self.renderer.invalidate()
            if self.objective.completion is not None:
                self.objective.completion.load_state(state.get("completion", {}))
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise FitError(
                f"{path}: cannot resume from this checkpoint ({type(exc).__name__}: {exc}); "
                "delete it, or fit without --resume"
            ) from None
        log.info("resumed from %s at stage %d step %d", path, self.stage, self.step)

    # ---- guard and previews -----------------------------------------------------------------------------
    def check(self) -> None:
        """Run the empty-render guard; after a restore, halve the learning rate and restart Adam."""
        event = self.guard.check()
        if event is None:
            return
        self.lr_scale *= 0.5
        self.stats.recoveries.append({"step": self.step, "stage": self.stage, **event, "lr_scale": self.lr_scale})
        log.warning(
            "empty render detected at stage %d step %d (input coverage %.3f, finite %s): restored the last good "
            "state, learning rate x%.3g",
            self.stage,
            self.step,
            event["coverage"],
            event["finite"],
            self.lr_scale,
        )
        self.make_optimizer()

    @torch.no_grad()
    def preview(self, tag: str) -> Path:
        """Input view (target | render) and three ring views, of the input pose and a mid-motion pose."""
        cam_in = self.views.input.camera
        cams = [cam_in.scaled(PREVIEW_SIZE / max(cam_in.width, cam_in.height))]
        ring = self.views.ring
        cams += [ring[round(k * len(ring) / 4)].scaled(PREVIEW_SIZE / ring[0].width) for k in (1, 2, 3)]
        target = F.interpolate(self.views.input.image[None], size=(cams[0].height, cams[0].width), mode="area")[0]
        tiles = [target.permute(1, 2, 0).cpu().numpy()]
        poses = self.views.poses[2]
        for pose in (self.renderer.input_pose, poses[len(poses) // 2]):
            tiles += [self.renderer.image(cam, pose) for cam in cams]
        h = max(t.shape[0] for t in tiles)
        tiles = [np.pad(t, ((0, h - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
        return write_image(self.run_dir / "previews" / f"{tag}.png", np.concatenate(tiles, 1))

    # ---- the loop ---------------------------------------------------------------------------------------
    def start_stage_2(self) -> None:
        self.stage, self.step = 2, 0
        if self.cfg.stage2_color == "part_mean":
            canon = self.subject.body.pose(self.subject.body.canonical_pose())
            colors = self.views.input.part_colors()
            self.avatar.field.set_colors_by_part(canon.vertices, self.subject.body.vertex_parts(), colors)
            log.info("stage 2 colours: reset to the input image's mean colour per body part")
        if self.hull is not None:
            self.avatar.field.fill(self.hull)
            log.info("stage 2 density: the room's hulls (%d cells) start opaque", int(self.hull.sum()))
        if self.objective.far_side.any():
            self.avatar.field.fill(self.objective.far_side)
            cells = int(self.objective.far_side.sum())
            log.info("stage 2 density: the far side's clothing (%d cells) starts opaque", cells)
        self.make_optimizer()

    def step_terms(self, stage: int) -> Terms | None:
        """One step's terms: stage 1's body-render patch, or stage 2's input patch or novel view."""
        if stage == 1:
            terms = self.objective.stage1()
        elif self.streams.sampling.random() < self.cfg.p_novel:
            terms = self.objective.novel_view()
        else:
            terms = self.objective.input_patch()
        return None if terms is None else {**terms, **self.objective.regularisers(stage, self.step)}

    def run_stage(self, stage: int, steps: int) -> None:
        cfg = self.cfg
        if self.stage > stage or steps <= 0:
            return
        if self.stage < stage:
            self.start_stage_2()
        start = time.perf_counter()
        self.guard.remember()
        meter = LossMeter(cfg.log_every)
        with tqdm(total=steps, initial=self.step, desc=f"stage {stage}", unit="step", dynamic_ncols=True) as bar:
            while self.step < steps:
                self.set_lr(self.step / max(1, steps))
                self.renderer.refresh(self.step)
                terms = self.step_terms(stage)
                if terms is None:
                    continue
                loss = self.objective.total(terms)
                self.opt.zero_grad(set_to_none=True)
                # A non-finite loss skips its update on the device (Adam's ``found_inf``), with no branch on its
                # value; the log read-out counts such steps and runs the guard.
                skipped = ~torch.isfinite(loss)
                self.opt.found_inf = skipped.float()
                self.objective.backward(loss)
                self.opt.step()
                self.step += 1
                bar.update(1)
                done = self.step == steps
                means = meter.add(terms, skipped)
                if done:
                    means = meter.read() or means
                if means is not None:
                    nonfinite = int(means.pop(NONFINITE))
                    self.stats.losses[f"stage{stage}"] = means
                    bar.set_postfix({k: f"{v:.3g}" for k, v in means.items()}, refresh=False)
                    write_json(self.run_dir / PROGRESS_FILE, {"stage": stage, "step": self.step, "steps": steps})
                    if nonfinite:
                        log.warning(
                            "stage %d: %d steps to %d had a non-finite loss; skipped", stage, nonfinite, self.step
                        )
                        self.check()
                if self.step % cfg.guard_every == 0 or done:
                    self.check()
                if self.step % cfg.preview_every == 0 or done:
                    self.preview(f"stage{stage}_{self.step:06d}")
                if self.step % cfg.checkpoint_every == 0 or done:
                    key = f"stage{stage}"
                    self.stats.seconds[key] = self.stats.seconds.get(key, 0.0) + time.perf_counter() - start
                    start = time.perf_counter()
                    self.save()

    @torch.enable_grad()
    def run(self, resume: bool = False) -> dict:
        """Train (continuing the run folder's checkpoint with ``resume``), save the avatar, write run.json. Gradients
        are on whatever the caller's mode (a script that renders under ``torch.set_grad_enabled(False)`` may fit).

        ``seconds`` in the report sum every run of the fit: set-up, and each stage up to its last checkpoint.
        """
        checkpoint = self.run_dir / CHECKPOINT
        if resume:
            if not checkpoint.is_file():
                raise FitError(f"{checkpoint}: no checkpoint to resume from; fit without --resume")
            prepare = self.stats.seconds["prepare"]
            self.resume()
            self.stats.seconds["prepare"] = self.stats.seconds.get("prepare", 0.0) + prepare
        elif checkpoint.exists():
            raise FitError(
                f"{self.run_dir} already holds a checkpoint: pass --resume to continue it, or use a new --out"
            )
        if self.cfg.body_prior:
            self.run_stage(1, self.cfg.init_steps)
        self.run_stage(2, self.cfg.steps)
        avatar_path = self.avatar.save(self.run_dir / AVATAR_FILE)
        seconds = self.stats.seconds
        seconds["total"] = sum(v for k, v in seconds.items() if k != "total")
        info, perceptual = self.objective.encoder_info, self.objective.perceptual
        report = {
            "subject": str(self.subject.root),
            "avatar": str(avatar_path),
            "config": config_dict(self.cfg),
            "encoder": info.to_dict() if info else None,
            "perceptual": {"name": perceptual.name, "reason": perceptual.reason},
            "training_poses": self.views.poses,
            "input_views": [[cam, frame] for cam, frame in self.subject.inputs],
            "observed_views": len(self.views.observed),
            "ring_cameras": len(self.views.ring),
            "seconds": seconds,
            "recoveries": self.stats.recoveries,
            "final_losses": self.stats.losses,
            "semantic_references_skipped": self.objective.skipped_references,
            "input_light": self.views.input.shading.to_dict(),
            "room_m": round(self.room.widest, 4),
            "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "device": str(self.device),
            "torch_threads": torch.get_num_threads(),
        }
        write_json(self.run_dir / "run.json", report)
        return report
