"""Fit configuration: one dataclass, named presets, TOML files and ``key=value`` overrides."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomllib

from .errors import ElicitError

ABLATIONS = (
    "none",
    "no_init",
    "no_semantic",
    "no_silhouette",
    "hard_silhouette",
    "no_hybrid_sampling",
    "input_pose_only",
)
BASELINES = ("none", "explicit_texture")


class ConfigError(ElicitError):
    """An unknown preset, key or value."""


@dataclass
class FitConfig:
    # --- avatar --------------------------------------------------------------------------------
    voxel_size: float = 0.016  # metres per canonical grid cell
    box_margin: float = 0.10  # clothing room around the canonical body, metres
    density_activation: str = "softplus"  # "relu" (HumanNeRF) or "softplus" (kinder to a grid)
    weight_grid: int = 32  # motion-weight volume resolution (per axis)
    learn_motion_weights: bool = False
    refine_input_pose: bool = False
    occupancy_cell: float = 0.04  # coarse occupancy cell for empty-space skipping, metres (0 = off)
    # --- rendering -----------------------------------------------------------------------------
    samples_per_ray: int = 48
    t_thresh: float = 1e-3  # early ray termination
    input_scale: float = 0.5  # the input image is used at this scale (HumanNeRF: 0.5)
    crop_size: int = 48  # side of training crops and patches, pixels (64: same novel-view quality, 30% slower)
    label_size: int = 256  # resolution of the body-prior label renders used to place crops
    # --- stage 1: body-render initialisation -----------------------------------------------------
    init_steps: int = 600
    init_frame_step: int = 4  # every k-th frame of the target motion
    init_cameras: int = 23
    init_lr: float = 0.08
    # After stage 1 the colour grid holds the template texture. "template" keeps it (the paper, whose
    # MLP spreads the input's colours to unseen areas by itself); "part_mean" resets every cell to the
    # input image's mean colour of its body part, since a grid has no such smoothness.
    stage2_color: str = "part_mean"
    # --- stage 2: one-shot training ----------------------------------------------------------------
    steps: int = 3000
    lr: float = 0.03
    lr_decay: float = 0.1  # total decay over the stage (exponential)
    stage2_density_lr: float = 1.0  # stage 2's density learning rate, as a multiple of lr (colour keeps lr)
    motion_weights_lr: float = 1e-3
    p_novel: float = 0.5
    train_frame_step: int = 4  # novel poses: every k-th frame of the target motion
    ring_cameras: int = 23
    part_min_pixels: int = 2000  # at 512x512; scaled with the label resolution
    # --- losses (paper weights; recon as HumanNeRF: perceptual 1.0 + MSE 0.2) ------------------------
    w_perceptual: float = 1.0
    w_mse: float = 0.2
    w_semantic: float = 0.1
    w_silhouette: float = 0.01
    w_edge: float = 0.01
    w_tv: float = 1e-2  # grid smoothness (no counterpart in the MLP-based paper)
    w_sparsity: float = 0.1  # stage 2: density outside the body costs a little (no counterpart in the paper)
    w_opacity: float = 0.2  # stage 2: binary-entropy prior on novel-view crop opacity (no counterpart in the paper)
    perceptual: str = "auto"  # "auto" (LPIPS if its weights are present, else SSIM), "lpips", "ssim"
    # --- semantic encoder --------------------------------------------------------------------------
    encoder: str = "auto"  # "auto", "clip" or "random-features"
    clip_model: str = "ViT-B-32"
    clip_pretrained: str = "openai"  # an open_clip tag or a local checkpoint file
    text_prompt: str = ""  # optional extra CLIP text reference (the paper's text guidance)
    w_text: float = 0.0
    # --- run control -------------------------------------------------------------------------------
    checkpoint_every: int = 200
    preview_every: int = 250
    seed: int = 0
    ablation: str = "none"
    baseline: str = "none"
    preset: str = "cpu-fast"
    extra: dict = field(default_factory=dict)

    def validate(self) -> FitConfig:
        if self.density_activation not in ("relu", "softplus"):
            raise ConfigError(f"density_activation must be relu or softplus, got {self.density_activation!r}")
        if self.encoder not in ("auto", "clip", "random-features"):
            raise ConfigError(f"encoder must be auto, clip or random-features, got {self.encoder!r}")
        if self.stage2_color not in ("template", "part_mean"):
            raise ConfigError(f"stage2_color must be template or part_mean, got {self.stage2_color!r}")
        if self.perceptual not in ("auto", "lpips", "ssim"):
            raise ConfigError(f"perceptual must be auto, lpips or ssim, got {self.perceptual!r}")
        if self.ablation not in ABLATIONS:
            raise ConfigError(f"ablation must be one of {ABLATIONS}, got {self.ablation!r}")
        if self.baseline not in BASELINES:
            raise ConfigError(f"baseline must be one of {BASELINES}, got {self.baseline!r}")
        for key in ("voxel_size", "crop_size", "samples_per_ray", "label_size", "weight_grid"):
            if getattr(self, key) <= 0:
                raise ConfigError(f"{key} must be positive, got {getattr(self, key)!r}")
        if not 0.0 <= self.p_novel <= 1.0:
            raise ConfigError(f"p_novel must be in [0, 1], got {self.p_novel}")
        return self


PRESETS: dict[str, dict[str, Any]] = {
    # Fits the demo subject in under 10 minutes on 2 CPU cores.
    "cpu-fast": {},
    # The paper's schedule, resolutions and samples (15k + 20k iterations, 224 crops, 128 samples,
    # ViT-L/14); meant for a GPU.
    "paper": {
        "voxel_size": 0.006,
        "samples_per_ray": 128,
        "t_thresh": 1e-4,
        "crop_size": 224,
        "label_size": 512,
        "init_steps": 15000,
        "init_frame_step": 10,
        "steps": 20000,
        "learn_motion_weights": True,
        "refine_input_pose": True,
        "clip_model": "ViT-L-14",
        "clip_pretrained": "openai",
        "checkpoint_every": 1000,
        "preview_every": 1000,
        "occupancy_cell": 0.02,
        "lr": 0.02,
        "init_lr": 0.05,
    },
}


def _coerce(key: str, raw: str, current: Any) -> Any:
    if isinstance(current, bool):
        if raw.lower() in ("1", "true", "yes", "on"):
            return True
        if raw.lower() in ("0", "false", "no", "off"):
            return False
        raise ConfigError(f"--set {key}: expected true or false, got {raw!r}")
    try:
        if isinstance(current, int):
            return int(raw)
        if isinstance(current, float):
            return float(raw)
    except ValueError:
        raise ConfigError(f"--set {key}: expected a {type(current).__name__}, got {raw!r}") from None
    return raw


def make_config(
    preset: str = "cpu-fast", toml_file: str | Path | None = None, overrides: list[str] | None = None
) -> FitConfig:
    """Preset, then a TOML file, then ``key=value`` overrides, in that order."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose from {sorted(PRESETS)}")
    cfg = FitConfig(**PRESETS[preset], preset=preset)
    names = {f.name for f in dataclasses.fields(FitConfig)}
    if toml_file is not None:
        path = Path(toml_file)
        if not path.is_file():
            raise ConfigError(f"{path}: config file not found")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML ({exc})") from exc
        for key, value in data.items():
            if key not in names:
                raise ConfigError(f"{path}: unknown config key {key!r}")
            setattr(cfg, key, value)
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"--set expects key=value, got {item!r}")
        key, raw = item.split("=", 1)
        key = key.strip()
        if key not in names:
            raise ConfigError(f"--set: unknown config key {key!r}")
        setattr(cfg, key, _coerce(key, raw.strip(), getattr(cfg, key)))
    return cfg.validate()


def config_dict(cfg: FitConfig) -> dict:
    return dataclasses.asdict(cfg)
