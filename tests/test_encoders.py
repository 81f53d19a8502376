"""Semantic encoders: open_clip mechanics with a tiny random model, and the named weights-free fallback."""

import json

import pytest
import torch

from elicit_diffrender.core.weights import resolve_clip_weights
from elicit_diffrender.model.encoders import FALLBACK_NAME, EncoderError, RandomFeatureEncoder, load_encoder

TINY = {
    "embed_dim": 32,
    "vision_cfg": {"image_size": 64, "layers": 2, "width": 64, "patch_size": 16, "head_width": 32},
    "text_cfg": {"context_length": 77, "vocab_size": 49408, "width": 64, "heads": 2, "layers": 2},
}


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    import open_clip

    root = tmp_path_factory.mktemp("clip")
    (root / "elicit-tiny-test.json").write_text(json.dumps(TINY))
    open_clip.add_model_config(root / "elicit-tiny-test.json")
    torch.manual_seed(0)
    model = open_clip.create_model("elicit-tiny-test", pretrained=None)
    path = root / "tiny.pt"
    torch.save(model.state_dict(), path)
    return path


def test_clip_from_a_local_checkpoint(tiny_checkpoint):
    enc, info = load_encoder("auto", "elicit-tiny-test", str(tiny_checkpoint))
    assert info.kind == "clip" and info.weights == str(tiny_checkpoint) and info.reason == ""
    assert enc.image_size == 64
    images = torch.rand(3, 3, 40, 40, requires_grad=True)
    emb = enc(images)
    assert emb.shape == (3, 32)
    torch.testing.assert_close(emb.norm(dim=1), torch.ones(3))
    emb[1].sum().backward()
    assert images.grad[1].abs().sum() > 0 and images.grad[0].abs().sum() == 0  # gradients reach the render
    text = enc.encode_text("a person wearing a striped shirt")
    assert text.shape == (32,)
    # The weights came from the file: a second load gives the same embedding.
    enc2, _ = load_encoder("clip", "elicit-tiny-test", str(tiny_checkpoint))
    torch.testing.assert_close(enc2(images.detach()), emb.detach())


def test_missing_weights_fall_back_by_name_or_fail(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty-hub"))
    monkeypatch.setenv("HOME", str(tmp_path))
    assert resolve_clip_weights("ViT-B-32", "openai") is None
    enc, info = load_encoder("auto", "ViT-B-32", "openai")
    assert enc is None and info.kind == "mirror" and info.name == FALLBACK_NAME and "no local weights" in info.reason
    with pytest.raises(EncoderError, match="no local weights"):
        load_encoder("clip", "ViT-B-32", "openai")
    with pytest.raises(EncoderError, match="no pretrained tag"):
        load_encoder("clip", "ViT-B-32", "not-a-tag")
    enc, info = load_encoder("random-features")
    assert isinstance(enc, RandomFeatureEncoder) and info.reason == "requested by config"
    enc, info = load_encoder("mirror")
    assert enc is None and info.name == FALLBACK_NAME and info.reason == "requested by config"


def test_fallback_is_colour_aware_and_masked():
    enc = RandomFeatureEncoder()
    green = torch.zeros(1, 3, 48, 48)
    green[:, 1] = 0.7
    red = torch.zeros(1, 3, 48, 48)
    red[:, 0] = 0.7
    noisy_green = (green + 0.05 * torch.randn_like(green)).clamp(0, 1)
    e = enc(torch.cat([green, noisy_green, red]))
    assert (e[0] @ e[1]) > (e[0] @ e[2]) + 0.3
    # With a mask, pixels outside the part do not count.
    half = green.clone()
    half[..., 24:] = red[..., 24:]
    mask = torch.zeros(1, 48, 48)
    mask[..., :24] = 1
    e_masked = enc(torch.cat([half, green]), torch.cat([mask, torch.ones(1, 48, 48)]))
    e_plain = enc(torch.cat([half, green]))
    assert (e_masked[0] @ e_masked[1]) > (e_plain[0] @ e_plain[1])
    with pytest.raises(EncoderError, match="text"):
        enc.encode_text("hello")
