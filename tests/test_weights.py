"""``elicit weights fetch/list`` against a local stand-in of the Hugging Face hub, with a tiny random open_clip
model; a fit then picks the fetched weights up with no flag."""

import hashlib
import http.server
import json
import os
import signal
import threading

import pytest
import torch

from elicit_diffrender.apps.cli import main
from elicit_diffrender.core.weights import resolve_clip_weights
from elicit_diffrender.model.encoders import load_encoder

TINY = {
    "embed_dim": 32,
    "vision_cfg": {"image_size": 64, "layers": 2, "width": 64, "patch_size": 16, "head_width": 32},
    "text_cfg": {"context_length": 77, "vocab_size": 49408, "width": 64, "heads": 2, "layers": 2},
}
MODEL, TAG, REPO = "elicit-tiny-weights", "standin", "elicit/tiny-weights"
COMMIT = "0" * 40


@pytest.fixture
def hub(tmp_path, monkeypatch):
    """A local HTTP server that answers the hub's resolve URLs for one repository holding a tiny model."""
    import open_clip
    from open_clip import pretrained
    from safetensors.torch import save_file

    (tmp_path / f"{MODEL}.json").write_text(json.dumps(TINY))
    open_clip.add_model_config(tmp_path / f"{MODEL}.json")
    torch.manual_seed(0)
    model = open_clip.create_model(MODEL, pretrained=None)
    blob = tmp_path / "served.safetensors"
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(blob))
    data = blob.read_bytes()
    etag = hashlib.sha256(data).hexdigest()
    requests = []
    # What the server answers; tests change it to play a hostile or broken server.
    serve = {"data": data, "etag": etag, "commit": COMMIT, "extra_length": 0}

    class Handler(http.server.BaseHTTPRequestHandler):
        def _head(self) -> bool:
            requests.append(self.path)
            served = (
                f"/{REPO}/resolve/main/open_clip_model.safetensors",
                f"/{etag}/tiny.safetensors",
                f"/{'0' * 64}/bad.safetensors",
            )
            if self.path not in served:
                self.send_response(404)
                self.send_header("Content-Length", "0")
                self.end_headers()
                return False
            self.send_response(200)
            self.send_header("Content-Length", str(len(serve["data"]) + serve["extra_length"]))
            self.send_header("ETag", f'"{serve["etag"]}"')
            self.send_header("X-Repo-Commit", serve["commit"])
            self.end_headers()
            return True

        def do_HEAD(self):  # noqa: N802 (http.server's names)
            self._head()

        def do_GET(self):  # noqa: N802
            if self._head():
                self.wfile.write(serve["data"])

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub-cache"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("HF_HUB_DISABLE_XET", "1")
    address = f"http://127.0.0.1:{server.server_address[1]}"
    # Tags with only a URL (OpenAI's style: the file's SHA-256 in its address), good and corrupt.
    urls = {"byurl": f"{address}/{etag}/tiny.safetensors", "badsha": f"{address}/{'0' * 64}/bad.safetensors"}
    monkeypatch.setitem(
        pretrained._PRETRAINED,
        MODEL,
        {TAG: pretrained._pcfg(hf_hub=f"{REPO}/"), **{t: pretrained._pcfg(url=u) for t, u in urls.items()}},
    )
    yield address, model, requests, serve
    server.shutdown()


def test_fetch_list_and_pick_up(hub, capsys):
    endpoint, model, requests, _ = hub
    assert resolve_clip_weights(MODEL, TAG) is None
    assert main(["weights", "list"]) == 0
    assert "no CLIP weights on disk" in capsys.readouterr().out
    assert main(["weights", "fetch", MODEL, TAG, "--endpoint", endpoint]) == 0
    out = capsys.readouterr().out
    assert requests and "hub-cache" in out
    path = resolve_clip_weights(MODEL, TAG)
    assert path is not None and path in out
    assert main(["weights", "list"]) == 0
    listing = capsys.readouterr().out
    assert f"{MODEL}/{TAG}" in listing and path in listing
    # A fit's default encoder mode finds the file with no flag, and it holds the served weights.
    enc, info = load_encoder("auto", MODEL, TAG)
    assert info.kind == "clip" and info.weights == path
    served = model.state_dict()
    for key, value in enc.model.state_dict().items():
        torch.testing.assert_close(value, served[key])


def test_fetch_failures_are_one_line(hub, capsys):
    endpoint, _, _, _ = hub
    assert main(["weights", "fetch", MODEL, "no-such-tag", "--endpoint", endpoint]) == 2
    err = capsys.readouterr().err.strip()
    assert "no pretrained tag 'no-such-tag'" in err and len(err.splitlines()) == 1


def test_fetch_by_url_checks_the_address_sha256(hub, tmp_path, capsys):
    assert main(["weights", "fetch", MODEL, "byurl"]) == 0
    path = resolve_clip_weights(MODEL, "byurl")
    assert (
        path is not None
        and path.startswith(str(tmp_path / "home" / ".cache" / "clip"))
        and path in capsys.readouterr().out
    )
    assert main(["weights", "fetch", MODEL, "badsha"]) == 2
    assert "does not match" in capsys.readouterr().err
    assert resolve_clip_weights(MODEL, "badsha") is None
    assert not list((tmp_path / "home" / ".cache" / "clip").glob(".*partial"))


def _files(root) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() or p.is_symlink()}


def test_server_headers_never_become_paths(hub, tmp_path, capsys):
    """An ETag of ``../../x`` and a commit of ``../../y`` wrote files of the server's choosing outside the cache."""
    endpoint, _, _, serve = hub
    serve["etag"], serve["commit"] = "../../x", "../../y"
    before = _files(tmp_path)
    assert main(["weights", "fetch", MODEL, TAG, "--endpoint", endpoint]) == 0
    added = _files(tmp_path) - before
    repo_folder = "hub-cache/models--elicit--tiny-weights/"
    assert added and all(p.startswith(repo_folder) for p in added), added
    assert not any(p.endswith(("/x", "/y")) or "/y/" in p for p in added), added
    path = resolve_clip_weights(MODEL, TAG)
    assert path is not None and hashlib.sha256(open(path, "rb").read()).hexdigest() in str(os.path.realpath(path))


def test_wrong_content_is_refused_and_not_stored(hub, tmp_path, capsys):
    """A server answering with other content: nothing stored, one line, and the next fit is not poisoned."""
    from safetensors.torch import save_file

    endpoint, _, _, serve = hub
    save_file({"visual.proj": torch.zeros(3)}, str(tmp_path / "wrong.safetensors"))
    for payload in ((tmp_path / "wrong.safetensors").read_bytes(), b"<html>rate limited</html>"):
        serve["data"], serve["etag"] = payload, hashlib.sha256(payload).hexdigest()
        assert main(["weights", "fetch", MODEL, TAG, "--endpoint", endpoint]) == 2
        err = capsys.readouterr().err.strip()
        assert "refused" in err and len(err.splitlines()) == 1, err
        assert resolve_clip_weights(MODEL, TAG) is None
        blobs = tmp_path / "hub-cache" / "models--elicit--tiny-weights" / "blobs"
        assert not blobs.exists() or not list(blobs.iterdir())
    assert main(["weights", "list"]) == 0 and "no CLIP weights on disk" in capsys.readouterr().out


def test_truncated_body_gives_up_and_leaves_nothing(hub, tmp_path, capsys):
    """A body shorter than its Content-Length was retried forever, leaving a large ``.incomplete`` file."""
    endpoint, _, requests, serve = hub
    serve["extra_length"] = 1000
    signal.signal(signal.SIGALRM, lambda *_: pytest.fail("the fetch retried for over 60 s"))
    signal.alarm(60)
    try:
        code = main(["weights", "fetch", MODEL, TAG, "--endpoint", endpoint])
    finally:
        signal.alarm(0)
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert "gave up after 3 attempts" in err and len(err.splitlines()) == 1, err
    assert len(requests) == 3
    left = [p for p in _files(tmp_path) if p.startswith("hub-cache")]
    assert not left, left


def test_poisoned_cache_falls_back_named_and_fetch_repairs_it(hub, capsys):
    """Bad bytes in the cache must not block a fit: ``auto`` reports the file and falls back; ``clip`` says why."""
    from elicit_diffrender.model.encoders import EncoderError

    endpoint, _, _, _ = hub
    assert main(["weights", "fetch", MODEL, TAG, "--endpoint", endpoint]) == 0
    path = resolve_clip_weights(MODEL, TAG)
    blob = os.path.realpath(path)
    with open(blob, "wb") as f:
        f.write(b"\x00" * 4096)
    enc, info = load_encoder("auto", MODEL, TAG)
    assert enc is None and info.kind == "mirror" and path in info.reason and "fell back" in info.reason
    with pytest.raises(EncoderError):
        load_encoder("clip", MODEL, TAG)
    capsys.readouterr()
    assert main(["weights", "fetch", MODEL, TAG, "--endpoint", endpoint]) == 0
    enc, info = load_encoder("auto", MODEL, TAG)
    assert info.kind == "clip"
