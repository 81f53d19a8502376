"""Fit configuration: one flat dataclass of typed keys, named presets, TOML files and ``key=value`` overrides.

Keys are flat (``--set w_semantic=0``, ``w_semantic = 0`` in TOML); the comments below group them.
``ablation=NAME`` is a shorthand, not a key: it expands to the switches of one of the paper's
ablations (``ABLATIONS``) at its place in the order preset, TOML file, overrides.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tomllib

from ..core.errors import ElicitError

# The paper's ablations (Table 4) as the switches they set.
ABLATIONS: dict[str, dict[str, Any]] = {
    "none": {},
    "no_init": {"body_prior": False},
    "no_semantic": {"w_semantic": 0.0},
    "no_silhouette": {"w_silhouette": 0.0, "w_edge": 0.0},
    "hard_silhouette": {"soft_silhouette": False},
    "no_hybrid_sampling": {"hybrid_sampling": False},
    "input_pose_only": {"train_poses": "input"},
}
CHOICES: dict[str, tuple[str, ...]] = {
    "density_activation": ("relu", "softplus"),
    "stage2_color": ("template", "part_mean"),
    "train_poses": ("motion", "input"),
    "perceptual": ("auto", "lpips", "ssim"),
    "encoder": ("auto", "clip", "mirror", "random-features"),
    "baseline": ("none", "explicit_texture"),
    "completion": ("mirror", "guarded"),
    "multi_photo": ("observed", "reference"),
}


class ConfigError(ElicitError):
    """An unknown preset, key or value."""


@dataclass
class FitConfig:
    # --- avatar --------------------------------------------------------------------------------
    voxel_size: float = 0.016  # metres per canonical grid cell
    box_margin: float = 0.10  # room around the canonical body (metres), grown where the input mask reaches further
    density_activation: str = "softplus"  # "relu" (HumanNeRF) or "softplus" (kinder to a grid)
    weight_grid: int = 32  # motion-weight volume resolution (per axis)
    # Exponent of the inverse warp's blend of bone candidates (1: HumanNeRF's weighted mean; larger: the
    # dominant bone decides, so candidates of distant bones do not average into ghost limbs)
    warp_sharpness: int = 4
    # Only bone candidates within this distance (metres) of the dominant bone's are blended (0: all), so a
    # hand hanging beside the hip is not averaged with the thigh into empty room (a dark fin there)
    warp_gate: float = 0.10
    # The motion weights of the room outside the body (hair, loose clothing), as a share of the body's (1: the
    # same). Below 1 a limb's own bones win the inverse warp over a neighbouring part's room (0.3 keeps the
    # torso beside a hanging arm out of the arm's room); the render scales the room's foreground back to 1
    room_weight: float = 1.0
    learn_motion_weights: bool = False
    refine_input_pose: bool = False  # learn a rotation correction per bone for every input pose
    # A multi-photo subject's other photos: "observed" views reconstructed in their own poses, or only semantic
    # "reference" crops (the paper's supplementary variant: no pose alignment, nothing reconstructed)
    multi_photo: str = "observed"
    garment_hull: bool = True  # a garment that bridges the legs in the photo gets depth (fit/room.py)
    hair_hull: bool = True  # hair that stands off the head in the photo stands off its back too (fit/room.py)
    # Metres of clothing on the body's far side in every photo, opaque from stage 2 on (fit/objective.py; 0: none)
    far_side_layer: float = 0.016
    occupancy_cell: float = 0.04  # coarse occupancy cell for empty-space skipping, metres (0 = off)
    # While the motion weights and a training pose are fixed, that pose's inverse warp is baked into a look-up
    # table with nodes this far apart (metres) and read trilinearly (0 = the exact per-bone warp for every sample)
    warp_cell: float = 0.02
    # --- rendering -----------------------------------------------------------------------------
    samples_per_ray: int = 48
    t_thresh: float = 1e-3  # early ray termination below this transmittance (0 = off)
    input_scale: float = 0.5  # the input image is used at this scale (HumanNeRF: 0.5)
    crop_size: int = 48  # side of training crops and patches, pixels
    label_size: int = 256  # side of the body-prior renders of the ring cameras, pixels
    # --- the paper's components (each off in one ablation) ---------------------------------------
    body_prior: bool = True  # density starts as the body and stage 1 runs (off: an empty grid, no stage 1)
    soft_silhouette: bool = True  # silhouette term punishes only missing density (off: plain MSE)
    hybrid_sampling: bool = True  # part- and rotation-aware novel views (off: whole body, uniform camera)
    train_poses: str = "motion"  # novel poses: "motion" (every k-th frame) or "input" (the input pose only)
    # --- stage 1: body-render initialisation -----------------------------------------------------
    # The grid starts as the body (``CanonicalField.init_from_body``), so stage 1 only softens it into what the
    # renders show; 150 steps scored as well as 600 (GT-body subjects 1 / 3 +0.10 / +0.13 dB) in a quarter of the time.
    init_steps: int = 150
    init_frame_step: int = 4  # stage 1 trains on every k-th frame of the target motion
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
    pose_lr: float = 1e-3  # learning rate of the input-pose correction
    p_novel: float = 0.5  # probability that a step is a novel view (else an input-image patch)
    train_frame_step: int = 4  # stage 2's novel poses: every k-th frame of the target motion
    ring_cameras: int = 23  # cameras of the ring around the body (stage 1 views, stage 2 novel views)
    part_min_pixels: int = 2000  # a body part smaller than this in a 512x512 image is not cropped (area-scaled)
    # --- losses: the weight of every term, by name (recon as HumanNeRF: perceptual 1.0 + MSE 0.2) ----
    w_perceptual: float = 1.0
    w_mse: float = 0.2
    w_init_alpha: float = 1.0  # stage 1: MSE of the rendered opacity against the body render's
    w_semantic: float = 0.1  # the semantic prior (0: off, with or without CLIP weights)
    w_mirror: float = 0.01  # the semantic prior's weights-free fallback (mirror completion), without CLIP weights
    # Where that fallback takes an unseen cell's colour (fit/completion.py): "mirror" (the cell's mirror image
    # through the body) or "guarded" (the mirror, but a source far in colour from what its band mostly shows, a
    # front-only detail, gives way to that; hair behind the ears)
    completion: str = "mirror"
    w_silhouette: float = 0.01
    w_edge: float = 0.01
    w_tv: float = 1e-2  # grid smoothness (no counterpart in the MLP-based paper)
    w_sparsity: float = 0.1  # stage 2: density outside the body costs a little (no counterpart in the paper)
    w_opacity: float = 0.2  # stage 2: binary-entropy prior on novel-view crop opacity (no counterpart in the paper)
    perceptual: str = "auto"  # "auto" (LPIPS if its weights are present, else SSIM), "lpips", "ssim"
    # --- semantic encoder --------------------------------------------------------------------------
    # "auto" (CLIP if its weights are on disk, else the mirror completion), "clip", "mirror" or
    # "random-features" (a weights-free embedding, for comparison)
    encoder: str = "auto"
    clip_model: str = "ViT-B-32"
    clip_pretrained: str = "openai"  # an open_clip tag or a local checkpoint file
    text_prompt: str = ""  # optional extra CLIP text reference (the paper's text guidance)
    w_text: float = 0.0
    # --- run control -------------------------------------------------------------------------------
    checkpoint_every: int = 500  # steps between checkpoints (about 10 s of a cpu-fast fit on 2 cores)
    preview_every: int = 500  # steps between preview images (never changes the fit)
    guard_every: int = 250  # steps between empty-render checks
    log_every: int = 25  # steps between loss read-outs (each one waits for the device)
    seed: int = 0
    baseline: str = "none"  # "explicit_texture": the paper's textured-body baseline instead of the avatar

    def validate(self) -> FitConfig:
        """Check choices and ranges; raises :class:`ConfigError` naming the key."""
        for key, allowed in CHOICES.items():
            if getattr(self, key) not in allowed:
                raise ConfigError(f"{key} must be one of {allowed}, got {getattr(self, key)!r}")
        for key, lo, hi in RANGES:
            value = getattr(self, key)
            if not lo <= value <= hi:
                raise ConfigError(f"{key} must be in [{lo}, {hi}], got {value!r}")
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ConfigError(f"{f.name} must be a finite number, got {value!r}")
            if f.name.startswith("w_") and value < 0:
                raise ConfigError(f"{f.name} must be >= 0, got {value!r}")
        return self


INF = float("inf")
RANGES: tuple[tuple[str, float, float], ...] = (
    ("voxel_size", 1e-3, 1.0),
    ("box_margin", 0.0, 1.0),
    ("weight_grid", 2, 256),
    ("warp_sharpness", 1, 16),
    ("warp_gate", 0.0, 1.0),
    ("room_weight", 0.01, 1.0),
    ("occupancy_cell", 0.0, 1.0),
    ("warp_cell", 0.0, 1.0),
    ("samples_per_ray", 1, 4096),
    ("t_thresh", 0.0, 0.5),
    ("input_scale", 1e-3, 1.0),
    ("crop_size", 4, 4096),
    ("label_size", 16, 4096),
    ("init_steps", 0, INF),
    ("init_frame_step", 1, INF),
    ("init_lr", 0.0, INF),
    ("steps", 0, INF),
    ("lr", 0.0, INF),
    ("lr_decay", 1e-9, 1.0),
    ("stage2_density_lr", 0.0, INF),
    ("motion_weights_lr", 0.0, INF),
    ("pose_lr", 0.0, INF),
    ("p_novel", 0.0, 1.0),
    ("train_frame_step", 1, INF),
    ("ring_cameras", 4, 360),
    ("part_min_pixels", 0, INF),
    ("checkpoint_every", 1, INF),
    ("preview_every", 1, INF),
    ("guard_every", 1, INF),
    ("log_every", 1, INF),
    ("seed", 0, 2**32 - 1),
)

PRESETS: dict[str, dict[str, Any]] = {
    # Fits the demo subject in a few minutes on 2 CPU cores.
    "cpu-fast": {},
    # The paper's schedule, resolutions and samples (15k + 20k iterations, stage 1 on every 10th frame,
    # 224 crops, 128 samples, ViT-L/14); meant for a GPU.
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
        "checkpoint_every": 1000,
        "preview_every": 1000,
        "guard_every": 1000,
        "occupancy_cell": 0.02,
        "lr": 0.02,
        "init_lr": 0.05,
    },
}
_TYPES = {name: hint for name, hint in typing.get_type_hints(FitConfig).items()}


def _typed(key: str, value: Any, where: str) -> Any:
    """``value`` as the type of ``key``: a string from ``--set`` is parsed, a TOML value is checked."""
    kind = _TYPES[key]
    if isinstance(value, str) and kind is not str:
        raw = value.strip()
        if kind is bool:
            if raw.lower() in ("1", "true", "yes", "on"):
                return True
            if raw.lower() in ("0", "false", "no", "off"):
                return False
        else:
            try:
                return kind(raw)
            except ValueError:
                pass
        raise ConfigError(f"{where}: {key} must be of type {kind.__name__}, got {value!r}")
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if type(value) is not kind:
        raise ConfigError(f"{where}: {key} must be of type {kind.__name__}, got {value!r}")
    return value


def _apply(cfg: FitConfig, key: str, value: Any, where: str) -> None:
    """Set one key, or expand the ``ablation`` shorthand into its switches."""
    if key == "ablation":
        if value not in ABLATIONS:
            raise ConfigError(f"{where}: ablation must be one of {tuple(ABLATIONS)}, got {value!r}")
        for k, v in ABLATIONS[value].items():
            setattr(cfg, k, v)
        return
    if key not in _TYPES:
        raise ConfigError(f"{where}: unknown config key {key!r}")
    setattr(cfg, key, _typed(key, value, where))


def make_config(
    preset: str = "cpu-fast", toml_file: str | Path | None = None, overrides: list[str] | None = None
) -> FitConfig:
    """Preset, then a TOML file, then ``key=value`` overrides, in that order."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose from {sorted(PRESETS)}")
    cfg = FitConfig(**PRESETS[preset])
    if toml_file is not None:
        path = Path(toml_file)
        if not path.is_file():
            raise ConfigError(f"{path}: config file not found")
        try:
            data = tomllib.loads(path.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: not valid TOML ({exc})") from exc
        for key, value in data.items():
            _apply(cfg, key, value, str(path))
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"--set expects key=value, got {item!r}")
        key, raw = item.split("=", 1)
        _apply(cfg, key.strip(), raw.strip(), "--set")
    return cfg.validate()


def config_dict(cfg: FitConfig) -> dict:
    return dataclasses.asdict(cfg)
