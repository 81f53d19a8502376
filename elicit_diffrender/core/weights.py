"""CLIP weights on disk: ``elicit weights fetch`` downloads open_clip weights on the user's request,
``elicit weights list`` shows what is there; a fit finds them by itself (:func:`resolve_clip_weights`).

Nothing else in the project downloads. Weights go where open_clip itself keeps them, so weights
that open_clip fetched before are found too: a tag with a Hugging Face hub repository into the hub
cache (``$HF_HUB_CACHE``, else ``$HF_HOME/hub``, else ``~/.cache/huggingface/hub``) as safetensors
(a format that cannot carry code); a tag with only a URL into ``~/.cache/clip``.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import tempfile
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


MAX_WEIGHTS_BYTES = 4 << 30  # larger than any open_clip checkpoint we use; a server sending more is refused
ATTEMPTS = 3  # downloads tried before giving up (a truncated or dropped body counts as one)
HEX40 = re.compile(r"[0-9a-f]{40}")
HEX64 = re.compile(r"[0-9a-f]{64}")


def fetch(model: str, tag: str, endpoint: str | None = None) -> Path:
    """Download the weights of open_clip's ``model``/``tag`` into the local cache and return the file.

    ``endpoint`` replaces the Hugging Face hub's address (a mirror), as ``$HF_ENDPOINT`` does. The server is not
    trusted: no path is built from what it sends (the blob is named by the SHA-256 we compute), the body must have
    the announced length, and what arrives must pass :func:`check_weights` (the architecture's tensor names and
    shapes) or, for a URL route, the SHA-256 in its address; a file that fails is deleted, never stored. A cached
    file that passes is reused.
    """
    cfg = pretrained_cfg(model, tag)
    source = hub_source(cfg)
    if source is None and not cfg.get("url"):
        raise WeightsError(f"open_clip's tag {model}/{tag} names neither a hub repository nor a URL")
    if source is None:
        return _fetch_url(cfg["url"], url_cache())
    cached = resolve_clip_weights(model, tag)
    if cached is not None and check_weights(model, Path(cached)) is None:
        return Path(cached)
    base = (endpoint or os.environ.get("HF_ENDPOINT") or "https://huggingface.co").rstrip("/")
    repo, filename = source
    root = hub_cache() / ("models--" + repo.replace("/", "--"))
    tmp, sha, headers = _download(f"{base}/{repo}/resolve/main/{filename}", root / "blobs")
    problem = check_weights(model, tmp)
    linked = headers.get("X-Linked-Etag", headers.get("ETag", "")).strip('"')
    if problem is None and HEX64.fullmatch(linked) and linked != sha:
        problem = f"its SHA-256 {sha} differs from the {linked} the server announced"
    if problem is not None:
        tmp.unlink(missing_ok=True)
        raise WeightsError(f"{base}/{repo}: refused the download: {problem}")
    commit = headers.get("X-Repo-Commit", "")
    return _store_hub(tmp, sha, root, commit if HEX40.fullmatch(commit) else sha[:40], filename)


def _download(url: str, folder: Path) -> tuple[Path, str, dict[str, str]]:
    """Stream ``url`` into a hidden ``.partial`` file in ``folder``: (file, SHA-256, response headers). A body
    shorter than its Content-Length, or a dropped connection, is retried up to :data:`ATTEMPTS` times; nothing is
    left behind on failure."""
    import http.client
    import urllib.error

    folder.mkdir(parents=True, exist_ok=True)
    last = ""
    for _ in range(ATTEMPTS):
        fd, name = tempfile.mkstemp(dir=folder, prefix=".download.", suffix=".partial")
        tmp = Path(name)
        try:
            digest, size = hashlib.sha256(), 0
            with os.fdopen(fd, "wb") as f, urllib.request.urlopen(url, timeout=60) as response:
                announced = response.headers.get("Content-Length", "")
                while chunk := response.read(1 << 20):
                    size += len(chunk)
                    if size > MAX_WEIGHTS_BYTES:
                        raise WeightsError(f"{url}: more than {MAX_WEIGHTS_BYTES >> 30} GiB; refused")
                    digest.update(chunk)
                    f.write(chunk)
                headers = dict(response.headers.items())
            if announced.isdigit() and size != int(announced):
                raise http.client.IncompleteRead(b"", int(announced) - size)
            return tmp, digest.hexdigest(), headers
        except urllib.error.HTTPError as exc:
            tmp.unlink(missing_ok=True)
            raise WeightsError(f"{url}: HTTP {exc.code} {exc.reason}") from None
        except ValueError as exc:  # an address urllib cannot use
            tmp.unlink(missing_ok=True)
            raise WeightsError(f"{url}: {exc}") from None
        except (OSError, http.client.HTTPException) as exc:
            tmp.unlink(missing_ok=True)
            last = f"{type(exc).__name__}: {str(exc)[:120]}"
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    raise WeightsError(f"{url}: gave up after {ATTEMPTS} attempts ({last})")


def _store_hub(tmp: Path, sha: str, root: Path, commit: str, filename: str) -> Path:
    """Move a checked download into the hub cache's layout (``blobs/SHA``, ``snapshots/COMMIT/FILE`` linking to it,
    ``refs/main``), where open_clip and :func:`resolve_clip_weights` find it."""
    blob = root / "blobs" / sha
    os.replace(tmp, blob)
    snapshot = root / "snapshots" / commit / filename
    snapshot.parent.mkdir(parents=True, exist_ok=True)
    link = snapshot.with_name(f".{filename}.link")
    link.unlink(missing_ok=True)
    link.symlink_to(os.path.relpath(blob, snapshot.parent))
    os.replace(link, snapshot)
    refs = root / "refs" / "main"
    refs.parent.mkdir(parents=True, exist_ok=True)
    refs_tmp = refs.with_name(".main.partial")
    refs_tmp.write_text(commit)
    os.replace(refs_tmp, refs)
    return snapshot


@functools.cache
def _tensor_shapes(model: str) -> dict[str, tuple[int, ...]]:
    """The name and shape of every tensor of open_clip's ``model`` (built once per process, randomly initialised)."""
    import open_clip

    return {k: tuple(v.shape) for k, v in open_clip.create_model(model, pretrained=None).state_dict().items()}


def check_weights(model: str, path: Path) -> str | None:
    """Why ``path`` cannot be ``model``'s weights, or None: it must be a safetensors file (a format that cannot carry
    code) holding every tensor of open_clip's ``model`` with its shape (the header is read; no tensor is loaded)."""
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            shapes = {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}
    except Exception as exc:  # safetensors raises its own error types for a bad header
        return f"not a safetensors file ({type(exc).__name__}: {str(exc)[:80]})"
    expected = _tensor_shapes(model)
    missing = [k for k in expected if k not in shapes]
    wrong = [k for k in expected if k in shapes and shapes[k] != expected[k]]
    if missing or wrong:
        first = (missing or wrong)[0]
        return f"{len(missing)} of {model}'s tensors missing and {len(wrong)} of another shape (first: {first})"
    return None


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def _fetch_url(url: str, folder: Path) -> Path:
    """Download ``url`` into ``folder`` atomically; the SHA-256 in the URL's path (OpenAI's style) is required and
    checked, also of a file already there (a mismatching one is downloaded again)."""
    expected = url.split("/")[-2] if len(url.split("/")) > 1 else ""
    if not HEX64.fullmatch(expected):
        raise WeightsError(f"{url}: no SHA-256 in the address to check the download against; refused")
    name = os.path.basename(url)
    if not name or name.startswith(".") or "\\" in name:
        raise WeightsError(f"{url}: no usable file name in the address")
    target = folder / name
    if target.is_file() and _sha256(target) == expected:
        return target
    tmp, actual, _ = _download(url, folder)
    if actual != expected:
        tmp.unlink(missing_ok=True)
        raise WeightsError(f"{url}: SHA-256 {actual} does not match the {expected} in its address")
    os.replace(tmp, target)
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
