"""CLIP weights on disk: ``elicit weights fetch`` downloads open_clip weights on the user's request,
``elicit weights list`` shows what is there; a fit finds them by itself (:func:`resolve_clip_weights`).

Nothing else in the project downloads. Weights go where open_clip itself keeps them, so weights
that open_clip fetched before are found too: a tag with a Hugging Face hub repository into the hub
cache (``$HF_HUB_CACHE``, else ``$HF_HOME/hub``, else ``~/.cache/huggingface/hub``) as safetensors
(a format that cannot carry code); a tag with only a URL into ``~/.cache/clip``.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import urllib.request
from dataclasses import dataclass
from pathlib import Path

from .errors import ElicitError

HUB_FILE = "open_clip_model.safetensors"


class WeightsError(ElicitError):
    """Weights that cannot be fetched."""


def hub_cache() -> Path:
    """The Hugging Face hub cache, from the environment at call time."""
    if os.environ.get("HF_HUB_CACHE"):
        return Path(os.environ["HF_HUB_CACHE"])
    home = os.environ.get("HF_HOME") or str(Path.home() / ".cache" / "huggingface")
    return Path(home) / "hub"


def url_cache() -> Path:
    """open_clip's cache for weights fetched by URL."""
    return Path.home() / ".cache" / "clip"


def pretrained_cfg(model: str, tag: str) -> dict:
    import open_clip

    cfg = open_clip.get_pretrained_cfg(model, tag)
    if not cfg:
        known = ", ".join(t for m, t in open_clip.list_pretrained() if m == model) or "none"
        raise WeightsError(f"open_clip has no pretrained tag {tag!r} for model {model!r} (its tags: {known})")
    return cfg


def hub_source(cfg: dict) -> tuple[str, str] | None:
    """(repository, file) of a tag's weights on the hub, or None."""
    hub = cfg.get("hf_hub", "")
    if not hub:
        return None
    repo, filename = os.path.split(hub)
    return repo, filename or HUB_FILE


def fetch(model: str, tag: str, endpoint: str | None = None) -> Path:
    """Download the weights of open_clip's ``model``/``tag`` into the local cache and return the file.

    ``endpoint`` replaces the Hugging Face hub's address (a mirror), as ``$HF_ENDPOINT`` does.
    """
    cfg = pretrained_cfg(model, tag)
    source = hub_source(cfg)
    try:
        if source is not None:
            from huggingface_hub import hf_hub_download

            path = hf_hub_download(
                source[0], source[1], cache_dir=hub_cache(), endpoint=endpoint or os.environ.get("HF_ENDPOINT")
            )
            return Path(path)
        if cfg.get("url"):
            return _fetch_url(cfg["url"], url_cache())
    except WeightsError:
        raise
    except Exception as exc:  # network, HTTP and file-system errors of two libraries
        raise WeightsError(f"cannot fetch {model}/{tag}: {type(exc).__name__}: {str(exc)[:200]}") from None
    raise WeightsError(f"open_clip's tag {model}/{tag} names neither a hub repository nor a URL")


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def _fetch_url(url: str, folder: Path) -> Path:
    """Download ``url`` into ``folder`` atomically; a SHA-256 in the URL's path (OpenAI's) is checked,
    also of a file already there (a mismatching one is downloaded again)."""
    folder.mkdir(parents=True, exist_ok=True)
    target = folder / os.path.basename(url)
    expected = url.split("/")[-2] if len(url.split("/")) > 1 else ""
    checked = len(expected) == 64
    if target.is_file() and (not checked or _sha256(target) == expected):
        return target
    with tempfile.NamedTemporaryFile(dir=folder, prefix=f".{target.name}.", suffix=".partial", delete=False) as tmp:
        try:
            with urllib.request.urlopen(url, timeout=60) as response:
                shutil.copyfileobj(response, tmp, 1 << 20)
        except BaseException:
            Path(tmp.name).unlink(missing_ok=True)
            raise
    actual = _sha256(Path(tmp.name))
    if checked and actual != expected:
        Path(tmp.name).unlink(missing_ok=True)
        raise WeightsError(f"{url}: SHA-256 {actual} does not match the {expected} in its address")
    os.replace(tmp.name, target)
    return target


def resolve_clip_weights(model: str, pretrained: str) -> str | None:
    """A local file for ``pretrained`` (a path, or an open_clip tag already in a cache), else None."""
    if Path(pretrained).expanduser().is_file():
        return str(Path(pretrained).expanduser())
    from huggingface_hub import try_to_load_from_cache

    try:
        cfg = pretrained_cfg(model, pretrained)
    except WeightsError as exc:
        raise WeightsError(f"{exc}, and no such file exists") from None
    if cfg.get("file"):
        return cfg["file"] if Path(cfg["file"]).is_file() else None
    source = hub_source(cfg)
    if source is not None:
        repo, filename = source
        names = [filename] if filename != HUB_FILE else [HUB_FILE, "open_clip_pytorch_model.bin"]
        for name in names:
            hit = try_to_load_from_cache(repo, name, cache_dir=hub_cache())
            if isinstance(hit, str):
                return hit
    url = cfg.get("url", "")
    if url:
        candidate = url_cache() / os.path.basename(url)
        if candidate.is_file():
            return str(candidate)
    return None


@dataclass
class OnDisk:
    model: str
    tag: str
    path: Path

    @property
    def megabytes(self) -> float:
        return self.path.stat().st_size / 2**20


def on_disk() -> list[OnDisk]:
    """Every open_clip (model, tag) whose weights are in the local caches."""
    import open_clip

    found = []
    for model, tag in open_clip.list_pretrained():
        path = resolve_clip_weights(model, tag)
        if path is not None:
            found.append(OnDisk(model, tag, Path(path)))
    return found
