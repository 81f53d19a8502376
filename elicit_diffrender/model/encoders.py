"""Semantic image encoders behind one interface: CLIP through open_clip, and a weights-free fallback.

``load_encoder`` never downloads: a pretrained tag is resolved to a file already in the local
caches (Hugging Face hub or ~/.cache/clip), or a checkpoint path is used directly. In ``auto`` mode,
when no CLIP weights are on disk, the semantic prior falls back to the weights-free mirror
completion (``fit.completion``, no encoder at all) and ``EncoderInfo`` says so, with the reason,
for every log, run.json and report. ``random-features`` is a weights-free image embedding kept
for comparison: matching its statistics paints blotches of colour on unseen sides.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from ..core.errors import ElicitError
from ..core.weights import WeightsError, resolve_clip_weights

CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
FALLBACK_NAME = "mirror completion (weights-free fallback)"
RANDOM_FEATURES_NAME = "random-features (weights-free)"


class EncoderError(ElicitError):
    """A requested encoder that cannot be built here."""


@dataclass
class EncoderInfo:
    name: str  # what is actually used, e.g. "clip ViT-B-32/openai" or the fallback's name
    kind: str  # "clip", "mirror" (no encoder) or "random-features"
    weights: str  # the file the weights came from ("" for the fallback)
    reason: str  # why the fallback was chosen ("" otherwise)

    def to_dict(self) -> dict:
        return asdict(self)


class ClipEncoder(nn.Module):
    """An open_clip image tower: resize to its input size, CLIP-normalise, embed, L2-normalise."""

    def __init__(self, model: nn.Module, tokenizer, image_size: int) -> None:
        super().__init__()
        self.model = model.eval()
        for p in self.model.parameters():
            p.requires_grad_(False)
        self.tokenizer = tokenizer
        self.image_size = image_size
        self.register_buffer("mean", torch.tensor(CLIP_MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(CLIP_STD).view(1, 3, 1, 1))

    def forward(self, images: torch.Tensor, masks: torch.Tensor | None = None) -> torch.Tensor:
        """(N, 3, H, W) in [0, 1] -> (N, D); CLIP sees whole crops, so ``masks`` are not used."""
        x = F.interpolate(images, size=(self.image_size, self.image_size), mode="bilinear", align_corners=False)
        return F.normalize(self.model.encode_image((x - self.mean) / self.std), dim=-1)

    @torch.no_grad()
    def encode_text(self, text: str) -> torch.Tensor:
        tokens = self.tokenizer([text]).to(self.mean.device)
        return F.normalize(self.model.encode_text(tokens), dim=-1)[0]


class RandomFeatureEncoder(nn.Module):
    """Weights-free appearance embedding, three equally weighted blocks: colour moments, a soft joint
    RGB histogram, and multi-scale statistics (mean, std) of fixed random convolution features. Each
    block is standardised against noise images and L2-normalised, then the whole is L2-normalised.
    With ``masks`` (the body part's pixels) every statistic is taken over the part only, so the
    colour statistics are per part.

    Translation invariant and pose tolerant, it compares the colours and textures of two crops of
    the same body part; it knows nothing of semantics, so it is only a fallback for CLIP.
    """

    def __init__(self, seed: int = 0, widths: tuple[int, ...] = (24, 48, 64), size: int = 96, bins: int = 4) -> None:
        super().__init__()
        gen = torch.Generator().manual_seed(seed)
        convs, c_in = [], 3
        for width in widths:
            conv = nn.Conv2d(c_in, width, 3, padding=1)
            with torch.no_grad():
                conv.weight.copy_(torch.randn(conv.weight.shape, generator=gen) * (2.0 / (9 * c_in)) ** 0.5)
                conv.bias.zero_()
            conv.requires_grad_(False)
            convs.append(conv)
            c_in = width
        self.convs = nn.ModuleList(convs)
        self.image_size = size
        centres = (torch.arange(bins, dtype=torch.float32) + 0.5) / bins
        grid = torch.stack(torch.meshgrid(centres, centres, centres, indexing="ij"), -1).reshape(-1, 3)
        self.register_buffer("bin_centres", grid)
        self.bin_width = 1.0 / bins
        with torch.no_grad():
            noise = torch.rand(64, 3, size, size, generator=gen)
            blocks = self._blocks(noise)
        for k, b in enumerate(blocks):
            self.register_buffer(f"centre{k}", b.mean(0))
            self.register_buffer(f"scale{k}", b.std(0).clamp(min=1e-4))
        self.n_blocks = len(blocks)

    @staticmethod
    def _moments(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        total = w.sum((2, 3)).clamp(min=1e-6)
        mean = (x * w).sum((2, 3)) / total
        var = ((x - mean[..., None, None]) ** 2 * w).sum((2, 3)) / total
        return torch.cat([mean, (var + 1e-8).sqrt()], 1)

    def _blocks(self, images: torch.Tensor, weights: torch.Tensor | None = None) -> list[torch.Tensor]:
        x = images
        w = torch.ones_like(x[:, :1]) if weights is None else weights
        moments = self._moments(x, w)
        pix = x.flatten(2).transpose(1, 2)  # (N, P, 3)
        d2 = ((pix[:, :, None, :] - self.bin_centres[None, None]) ** 2).sum(-1)
        soft = torch.softmax(-d2 / (2 * (0.5 * self.bin_width) ** 2), dim=-1)
        wp = w.flatten(2).transpose(1, 2)  # (N, P, 1)
        hist = (soft * wp).sum(1) / wp.sum(1).clamp(min=1e-6)
        feats = []
        x = (x - 0.5) / 0.25
        for conv in self.convs:
            x = F.relu(conv(x))
            feats.append(self._moments(x, w))
            x = F.avg_pool2d(x, 2)
            w = F.avg_pool2d(w, 2)
        return [moments, hist, torch.cat(feats, 1)]

    def forward(self, images: torch.Tensor, masks: torch.Tensor | None = None) -> torch.Tensor:
        """(N, 3, H, W) in [0, 1], optional (N, H, W) part masks -> (N, D)."""
        size = (self.image_size, self.image_size)
        x = F.interpolate(images, size=size, mode="bilinear", align_corners=False)
        w = (
            None
            if masks is None
            else F.interpolate(masks[:, None].float(), size=size, mode="bilinear", align_corners=False)
        )
        blocks = self._blocks(x, w)
        parts = [
            F.normalize((b - getattr(self, f"centre{k}")) / getattr(self, f"scale{k}"), dim=-1)
            for k, b in enumerate(blocks)
        ]
        return F.normalize(torch.cat(parts, 1), dim=-1)

    def encode_text(self, text: str) -> torch.Tensor:
        raise EncoderError(f"{RANDOM_FEATURES_NAME} has no text tower; text prompts need CLIP weights")


def weights_problem(model: str, weights: str) -> str:
    """Why ``weights`` cannot be read, found before the model is built ("" if no reason is known): a plain pickle
    must pass torch's weights-only loader. Safetensors files, zip checkpoints and TorchScript archives are left
    to open_clip, which reads them into the model it builds (building one more model to check them first would
    double every fit's encoder start-up)."""
    path = Path(weights)
    with open(path, "rb") as f:
        head = f.read(4)
    if head == b"PK\x03\x04" or path.suffix == ".safetensors":
        return ""
    try:
        torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for a file it will not unpickle
        return f"{type(exc).__name__}: {' '.join(str(exc).split())[:200]}"
    return ""


def build_clip(model: str, weights: str | None, quick_gelu: bool = False) -> ClipEncoder:
    """An open_clip model from a local weights file (or randomly initialised when ``weights`` is None); a file
    that cannot be read is refused before the model is built (:func:`weights_problem`)."""
    import open_clip

    problem = weights_problem(model, weights) if weights is not None else ""
    if problem:
        raise EncoderError(f"cannot build open_clip {model!r} from {weights!r}: {problem}")

    try:
        net, _, preprocess = open_clip.create_model_and_transforms(
            model, pretrained=weights, force_quick_gelu=quick_gelu
        )
    except Exception as exc:  # open_clip raises assorted errors for unknown models or bad files
        raise EncoderError(f"cannot build open_clip {model!r} from {weights!r}: {exc}") from exc
    size = net.visual.image_size
    size = size[0] if isinstance(size, (tuple, list)) else int(size)
    return ClipEncoder(net, open_clip.get_tokenizer(model), size)


def load_encoder(
    kind: str = "auto", model: str = "ViT-B-32", pretrained: str = "openai"
) -> tuple[nn.Module | None, EncoderInfo]:
    """The semantic encoder (None for the mirror completion) and a record of what was used: ``auto``
    falls back to the mirror completion without weights or with weights that do not load (a poisoned cache), and
    says which in the record's reason."""
    if kind == "random-features":
        return RandomFeatureEncoder(), EncoderInfo(RANDOM_FEATURES_NAME, "random-features", "", "requested by config")
    if kind == "mirror":
        return None, EncoderInfo(FALLBACK_NAME, "mirror", "", "requested by config")
    if kind not in ("auto", "clip"):
        raise EncoderError(f"unknown encoder {kind!r}; use auto, clip, mirror or random-features")
    try:
        weights = resolve_clip_weights(model, pretrained)
    except WeightsError as exc:
        raise EncoderError(str(exc)) from None
    if weights is None:
        reason = (
            f"no local weights for open_clip {model}/{pretrained} (nothing is downloaded at run time; pass a "
            f"checkpoint path with --set clip_pretrained=/path/to/weights)"
        )
        if kind == "clip":
            raise EncoderError(reason)
        return None, EncoderInfo(FALLBACK_NAME, "mirror", "", reason)
    import open_clip

    cfg = open_clip.get_pretrained_cfg(model, pretrained) if not Path(pretrained).expanduser().is_file() else {}
    try:
        encoder = build_clip(model, weights, quick_gelu=bool(cfg.get("quick_gelu", False)))
    except EncoderError as exc:
        if kind == "clip":
            raise
        reason = f"the weights file {weights} cannot be loaded ({str(exc)[-160:]}); fell back to the mirror completion"
        return None, EncoderInfo(FALLBACK_NAME, "mirror", "", reason)
    return encoder, EncoderInfo(f"clip {model}/{Path(pretrained).name}", "clip", weights, "")
