"""The fit: crop cameras, avatar files, config, the empty-render guard, a tiny end-to-end fit, kill and resume."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from devices import DEVICE

from elicit_diffrender.body import PART_NAMES
from elicit_diffrender.core.io import read_tensors, write_tensors
from elicit_diffrender.data.subject import SubjectError, load_subject
from elicit_diffrender.fit.checkpoint import CHECKPOINT, FitError, read_checkpoint
from elicit_diffrender.fit.config import ConfigError, make_config
from elicit_diffrender.fit.trainer import Trainer
from elicit_diffrender.fit.views import crop_image
from elicit_diffrender.model.avatar import Avatar, AvatarError
from elicit_diffrender.model.field import grid_points
from elicit_diffrender.model.load import load_avatar
from elicit_diffrender.model.skinning import lookup_baked_warp
from elicit_diffrender.model.volume import BakedWarp
from elicit_diffrender.outputs.evaluate import psnr

TINY = [
    "init_steps=30",
    "steps=40",
    "crop_size=32",
    "label_size=96",
    "voxel_size=0.03",
    "samples_per_ray=24",
    "ring_cameras=8",
    "occupancy_cell=0.06",
    "preview_every=1000",
    "checkpoint_every=10",
    "weight_grid=16",
]


@pytest.fixture(scope="module")
def tiny_avatar(tiny_subject):
    cfg = make_config("cpu-fast", None, TINY)
    return Avatar.from_body(
        tiny_subject.body, tiny_subject.body_spec, cfg.voxel_size, occupancy_cell=0.06, weight_res=16
    ).to(DEVICE)


def test_crop_camera_renders_exactly_the_crop(tiny_subject, tiny_avatar):
    cam = tiny_subject.cameras["cam00"]
    frames = tiny_avatar.bone_transforms(*tiny_subject.motion.frame(0))
    full = tiny_avatar.render_image(cam, frames, 32)
    x0, y0, side = 30, 20, 40
    crop = tiny_avatar.render_image(cam.crop(x0, y0, side, side, side), frames, 32)
    np.testing.assert_allclose(crop["rgb"], full["rgb"][y0 : y0 + side, x0 : x0 + side], atol=1e-5)
    # And the image-side crop helper samples the same window.
    img = torch.as_tensor(full["rgb"]).permute(2, 0, 1)
    np.testing.assert_allclose(
        crop_image(img, (x0, y0, side), side).permute(1, 2, 0).numpy(),
        full["rgb"][y0 : y0 + side, x0 : x0 + side],
        atol=1e-5,
    )


def test_without_occupancy_skipping_the_body_is_still_rendered(tiny_subject, tiny_avatar):
    """occupancy_cell=0 bounds the whole canonical box: same image as with skipping, never an empty one."""
    cfg = make_config("cpu-fast", None, TINY)
    plain = Avatar.from_body(tiny_subject.body, tiny_subject.body_spec, cfg.voxel_size, occupancy_cell=0, weight_res=16)
    cam = tiny_subject.cameras["cam00"].scaled(0.5)
    frames = plain.bone_transforms(*tiny_subject.motion.frame(3))
    box, occ = plain.observation_space(frames)
    skip_box, _ = tiny_avatar.observation_space(frames)
    slack = 0.03  # pads and lattice offsets follow the cell: 6 cm cells (skipping) against 4 cm (bounds)
    assert occ is None and (box[0] <= skip_box[0] + slack).all() and (box[1] >= skip_box[1] - slack).all()
    a = plain.render_image(cam, frames, 64)["alpha"]
    b = tiny_avatar.render_image(cam, frames, 64)["alpha"]
    assert a.mean() > 0.05
    assert np.abs(a - b).mean() < 0.02


def test_a_baked_warp_renders_like_the_exact_one(tiny_subject, tiny_avatar):
    """A pose's warp baked into a 2 cm look-up table: near the body the canonical points are those of the exact
    warp (the warp is rigid within each bone's region), and the render barely changes. The fit bakes only
    poses whose warp is fixed."""
    from elicit_diffrender.fit.render import PoseRenderer
    from elicit_diffrender.fit.streams import RandomStreams

    avatar, subject = tiny_avatar, tiny_subject
    bones = avatar.bone_transforms(*subject.motion.frame(3))
    box, _ = avatar.observation_space(bones)
    table = avatar.bake_warp(bones, box, 0.02)
    assert table.shape == (*(int(n) for n in ((box[1] - box[0]) / 0.02).ceil() + 1), 4)
    verts = torch.as_tensor(subject.body.pose(*subject.motion.frame(3)).vertices, dtype=torch.float32)
    near = verts + 0.02 * torch.randn(verts.shape, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        exact, fg_exact = avatar.warp_points(near, bones)
        looked, fg_table = lookup_baked_warp(near, table, box)
        fg_looked = avatar.foreground(fg_table)
    err = (looked - exact).norm(dim=1)[fg_exact > 0.5]
    assert err.median() < 1e-3 and (err > 0.01).float().mean() < 0.01, (err.median(), (err > 0.01).float().mean())
    assert (fg_looked - fg_exact).abs().mean() < 0.02
    none, fg_none = lookup_baked_warp(torch.zeros(0, 3), table, box)  # a crop that misses the body
    assert none.shape == (0, 3) and none.is_contiguous() and fg_none.shape == (0,)
    cam = subject.cameras["cam01"].scaled(0.5)
    origins, dirs = cam.rays()
    with torch.no_grad():
        a = avatar.render_rays(origins, dirs, bones, 32, torch.zeros(3))
        b = avatar.render_rays(origins, dirs, bones, 32, torch.zeros(3), warp=BakedWarp(table, box))
    assert a["alpha"].mean() > 0.04
    assert (a["alpha"] - b["alpha"]).abs().mean() < 0.01 and (a["rgb"] - b["rgb"]).abs().mean() < 0.01
    # The fit's renderer bakes fixed warps only: not while the motion weights learn, not the refined input pose.
    poses = [subject.input_index, 3]
    learned = avatar.motion_weights.logits.requires_grad
    try:
        avatar.motion_weights.logits.requires_grad_(False)
        renderer = PoseRenderer(avatar, subject, poses, 24, 1e-3, RandomStreams.from_seed(0), warp_cell=0.02)
        assert renderer.baked(3) is not None and renderer.baked(subject.input_index) is not None
        assert PoseRenderer(avatar, subject, poses, 24, 1e-3, RandomStreams.from_seed(0)).baked(3) is None
        avatar.motion_weights.logits.requires_grad_(True)
        assert renderer.baked(3) is None
    finally:
        avatar.motion_weights.logits.requires_grad_(learned)


def test_avatar_file_round_trip(tmp_path, tiny_subject, tiny_avatar):
    path = tiny_avatar.save(tmp_path / "avatar.safetensors")
    back = load_avatar(path)
    cam = tiny_subject.cameras["cam01"].scaled(0.5)
    bones = back.bone_transforms(*tiny_subject.motion.frame(2))
    expected = tiny_avatar.render_image(cam, bones, 24)["rgb"]
    np.testing.assert_array_equal(back.render_image(cam, bones, 24)["rgb"], expected)
    data = read_tensors(path)
    assert data["format"] == "elicit-avatar/2" and data["body"]["model"] == "anny"
    # An elicit-avatar/1 file of earlier versions (torch's format, older tensor names) still loads, safely.
    legacy = tiny_avatar.state()
    tensors = dict(legacy["tensors"])
    tensors["canonical_frames"] = tensors.pop("canonical_bones")
    tensors["clothing_room"] = tensors["field.occupancy"].clone()
    torch.save({**legacy, "format": "elicit-avatar/1", "tensors": tensors}, tmp_path / "avatar.pt")
    old = load_avatar(tmp_path / "avatar.pt")
    np.testing.assert_array_equal(old.render_image(cam, bones, 24)["rgb"], expected)
    del data["voxel_size"]
    write_tensors(tmp_path / "missing.safetensors", data)
    with pytest.raises(AvatarError, match=r"without the field\(s\) \['voxel_size'\]"):
        load_avatar(tmp_path / "missing.safetensors")
    (tmp_path / "bad.safetensors").write_bytes(b"junk")
    with pytest.raises(AvatarError, match="unreadable avatar file"):
        load_avatar(tmp_path / "bad.safetensors")


def test_the_refined_input_pose_travels_with_the_avatar(tmp_path, tiny_subject):
    """A fit with ``refine_input_pose`` learns a correction, and the saved avatar renders the input pose (only)
    with it: in ``render``, ``eval`` and the export alike, which all take bones from ``bone_transforms``."""
    cfg = make_config("cpu-fast", None, TINY + ["refine_input_pose=true", "pose_lr=0.01"])
    trainer = Trainer(tiny_subject, cfg, tmp_path / "run")
    trainer.run()
    assert trainer.avatar.pose_delta.abs().max() > 1e-3
    back = load_avatar(tmp_path / "run")
    inp, other = tiny_subject.motion.frame(tiny_subject.input_index), tiny_subject.motion.frame(2)
    raw = back.bone_transforms(*inp, refine=False)
    torch.testing.assert_close(back.bone_transforms(*inp), back.refined(raw))
    assert (back.bone_transforms(*inp) - raw).abs().max() > 1e-4
    torch.testing.assert_close(back.bone_transforms(*other), back.bone_transforms(*other, refine=False))
    # A file from before multi-photo fits held one correction, (B, 3), and one flat pose: it loads as row 0.
    legacy = back.state()
    legacy["tensors"]["pose_delta"] = legacy["tensors"]["pose_delta"][0]
    legacy["tensors"]["refined_pose"] = legacy["tensors"]["refined_pose"][0]
    old = Avatar.from_state(legacy).to(back.device)
    torch.testing.assert_close(old.bone_transforms(*inp), back.bone_transforms(*inp))
    # An avatar fitted without it (or saved before the key existed) renders every pose as given.
    state = back.state()
    del state["tensors"]["refined_pose"]
    plain = Avatar.from_state(state).to(back.device)
    torch.testing.assert_close(plain.bone_transforms(*inp), raw)


def test_a_body_outside_the_input_view_is_refused(tmp_path, tiny_subject):
    import shutil

    root = shutil.copytree(tiny_subject.root, tmp_path / "s")
    m = dict(np.load(root / "motion.npz"))
    m["transl"] = m["transl"] + np.array([20.0, 0.0, 0.0])  # 20 m to the side: nothing left in the photo
    np.savez(root / "motion.npz", **m)
    with pytest.raises(SubjectError, match="covers 0% of the input mask"):
        Trainer(load_subject(root), make_config("cpu-fast", None, TINY), tmp_path / "run")


def test_config_presets_files_and_overrides(tmp_path):
    cfg = make_config("paper")
    assert cfg.steps == 20000 and cfg.init_steps == 15000 and cfg.crop_size == 224 and cfg.clip_model == "ViT-L-14"
    assert cfg.init_frame_step == 10 and cfg.train_frame_step == 4
    (tmp_path / "c.toml").write_text('steps = 12\nencoder = "random-features"\nlr = 1\n')
    cfg = make_config("cpu-fast", tmp_path / "c.toml", ["lr=0.5", "refine_input_pose=true"])
    assert cfg.steps == 12 and cfg.encoder == "random-features" and cfg.lr == 0.5 and cfg.refine_input_pose
    for bad, message in (
        (["nope=1"], "unknown config key"),
        (["steps=many"], "steps must be of type int"),
        (["ablation=wild"], "ablation must be one of"),
        (["steps"], "key=value"),
        (["checkpoint_every=0"], r"checkpoint_every must be in \[1"),
        (["w_mse=-1"], "w_mse must be >= 0"),
        (["train_poses=some"], "train_poses must be one of"),
    ):
        with pytest.raises(ConfigError, match=message):
            make_config("cpu-fast", None, bad)
    with pytest.raises(ConfigError, match="unknown preset"):
        make_config("fast")
    (tmp_path / "bad.toml").write_text('voxel_size = "x"\n')
    with pytest.raises(ConfigError, match=r"bad\.toml: voxel_size must be of type float, got 'x'"):
        make_config("cpu-fast", tmp_path / "bad.toml")
    (tmp_path / "bool.toml").write_text("steps = true\n")
    with pytest.raises(ConfigError, match="steps must be of type int"):
        make_config("cpu-fast", tmp_path / "bool.toml")


def test_ablation_shorthand_expands_to_switches(tmp_path):
    """Each of the paper's ablations is a named set of switches, from --set and from TOML alike."""
    assert not make_config("cpu-fast", None, ["ablation=no_init"]).body_prior
    assert make_config("cpu-fast", None, ["ablation=no_semantic"]).w_semantic == 0
    cfg = make_config("cpu-fast", None, ["ablation=no_silhouette"])
    assert cfg.w_silhouette == 0 and cfg.w_edge == 0
    assert not make_config("cpu-fast", None, ["ablation=hard_silhouette"]).soft_silhouette
    assert not make_config("cpu-fast", None, ["ablation=no_hybrid_sampling"]).hybrid_sampling
    assert make_config("cpu-fast", None, ["ablation=input_pose_only"]).train_poses == "input"
    (tmp_path / "a.toml").write_text('ablation = "no_init"\n')
    assert not make_config("cpu-fast", tmp_path / "a.toml").body_prior
    # Later keys override the shorthand's switches.
    assert make_config("cpu-fast", None, ["ablation=no_semantic", "w_semantic=0.3"]).w_semantic == 0.3
    assert "ablation" not in make_config("cpu-fast").__dict__


def test_empty_render_guard_restores_and_lowers_the_lr(tmp_path, tiny_subject):
    cfg = make_config("cpu-fast", None, TINY)
    trainer = Trainer(tiny_subject, cfg, tmp_path / "run")
    trainer.guard.remember()
    assert trainer.guard.coverage() > 0.5
    with torch.no_grad():
        trainer.avatar.field.density.fill_(-40.0)  # the avatar went empty
    assert trainer.guard.coverage() < 0.01
    trainer.check()
    assert trainer.guard.coverage() > 0.5 and trainer.lr_scale == 0.5
    assert len(trainer.stats.recoveries) == 1


def test_guard_lets_an_empty_start_grow_but_catches_it_emptying(tmp_path, tiny_subject):
    cfg = make_config("cpu-fast", None, TINY + ["ablation=no_init"])
    trainer = Trainer(tiny_subject, cfg, tmp_path / "run")
    trainer.guard.remember()
    start = trainer.guard.coverage()
    assert 0.0 < start < 0.2  # the grid starts (almost) empty without the body prior
    trainer.check()
    assert not trainer.stats.recoveries  # low coverage alone is no collapse
    with torch.no_grad():
        trainer.avatar.field.density.fill_(-40.0)
    trainer.check()
    assert len(trainer.stats.recoveries) == 1 and trainer.guard.coverage() == pytest.approx(start)


def test_stage2_density_lr_scales_only_the_density(tmp_path, tiny_subject):
    cfg = make_config("cpu-fast", None, TINY + ["stage2_density_lr=0.1"])
    trainer = Trainer(tiny_subject, cfg, tmp_path / "run")
    lrs = {id(g["params"][0]): g["lr"] for g in trainer.opt.param_groups}
    field = trainer.avatar.field
    assert lrs[id(field.density)] == lrs[id(field.color)] == cfg.init_lr  # stage 1 is untouched
    trainer.stage = 2
    trainer.make_optimizer()
    lrs = {id(g["params"][0]): g["lr"] for g in trainer.opt.param_groups}
    assert lrs[id(field.density)] == pytest.approx(0.1 * cfg.lr) and lrs[id(field.color)] == cfg.lr


def test_unusable_checkpoint_gives_a_clear_error(tmp_path, tiny_subject):
    cfg = make_config("cpu-fast", None, TINY)
    run = tmp_path / "run"
    trainer = Trainer(tiny_subject, cfg, run)
    trainer.save()
    data = read_tensors(run / CHECKPOINT)
    # An older layout: density and colour in one parameter group.
    groups = data["optimizer"]["param_groups"]
    groups[0]["params"] += groups.pop(1)["params"]
    write_tensors(run / CHECKPOINT, data)
    with pytest.raises(FitError, match=r"checkpoint\.safetensors: cannot resume"):
        trainer.resume()
    write_tensors(run / CHECKPOINT, {"format": "elicit-checkpoint/1", "step": 3})
    with pytest.raises(FitError, match=r"not an elicit-checkpoint/2 checkpoint"):
        trainer.resume()
    (run / CHECKPOINT).write_bytes(b"junk")
    with pytest.raises(FitError, match=r"checkpoint\.safetensors: cannot resume"):
        trainer.resume()
    (run / CHECKPOINT).unlink()
    with pytest.raises(FitError, match="no checkpoint to resume from"):
        trainer.run(resume=True)


class StopAt(Trainer):
    """A trainer that keeps a copy of its checkpoint at one stage-2 step (a kill, in effect)."""

    keep_step = 20

    def save(self) -> None:
        super().save()
        if self.stage == 2 and self.step == self.keep_step:
            (self.run_dir / "kept.safetensors").write_bytes((self.run_dir / CHECKPOINT).read_bytes())


def same_fit(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Bit for bit on the CPU. On CUDA the kernels' gradient sums are atomic adds in no fixed order, so two runs
    of the same fit agree to rounding, not bitwise."""
    if a.device.type == "cpu":
        return torch.equal(a, b)
    return torch.allclose(a, b, rtol=1e-3, atol=1e-3)


def test_previews_and_resume_never_change_the_avatar(tmp_path, tiny_subject):
    """Same seed, same avatar: with another preview cadence, and when resumed from a checkpoint (bit for bit on the
    CPU)."""
    base = TINY + ["steps=30", "guard_every=15"]
    a = StopAt(tiny_subject, make_config("cpu-fast", None, base + ["preview_every=7"]), tmp_path / "a")
    a.run()
    b = Trainer(tiny_subject, make_config("cpu-fast", None, base + ["preview_every=1000"]), tmp_path / "b")
    b.run()
    assert len(list((tmp_path / "a" / "previews").glob("*.png"))) > len(list((tmp_path / "b" / "previews").glob("*")))
    for k, v in a.avatar.state_dict().items():
        assert same_fit(v, b.avatar.state_dict()[k]), k
    # Resume from a's step-20 checkpoint in a fresh folder: the same avatar as a's uninterrupted fit.
    c_dir = tmp_path / "c"
    c_dir.mkdir()
    (c_dir / CHECKPOINT).write_bytes((tmp_path / "a" / "kept.safetensors").read_bytes())
    assert read_checkpoint(c_dir)["step"] == 20
    c = Trainer(tiny_subject, make_config("cpu-fast", None, base + ["preview_every=1000"]), c_dir)
    report = c.run(resume=True)
    for k, v in a.avatar.state_dict().items():
        assert same_fit(v, c.avatar.state_dict()[k]), k
    # Stage times add up over both runs: stage 1 ran only in a's, and still counts.
    assert report["seconds"]["stage1"] > 0 and report["seconds"]["total"] >= report["seconds"]["stage2"]


def test_tiny_fit_improves_the_input_view(tmp_path, tiny_subject):
    cfg = make_config("cpu-fast", None, TINY + ["p_novel=0.3"])
    trainer = Trainer(tiny_subject, cfg, tmp_path / "run")
    cam = trainer.views.input.camera
    target = trainer.views.input.image.permute(1, 2, 0).cpu().numpy()
    mask = np.ones(target.shape[:2], bool)

    def input_psnr():
        return psnr(trainer.renderer.image(cam, tiny_subject.input_index), target, mask)

    trainer.run_stage(1, cfg.init_steps)
    after_init = input_psnr()  # the template-textured body
    trainer.run_stage(2, 150)
    after_fit = input_psnr()
    assert after_fit > after_init + 2.0, (after_init, after_fit)


def test_a_photo_patch_leaves_the_colour_behind_the_body_to_the_completion(tmp_path, tiny_subject):
    """Through a see-through avatar a photo's rays reach the back; the completed cells behind the body take no colour
    gradient from them, while the completion's own term still reaches those cells."""
    cfg = make_config("cpu-fast", None, TINY + ["encoder=mirror"])
    trainer = Trainer(tiny_subject, cfg, tmp_path / "run")
    objective, field = trainer.objective, trainer.avatar.field
    behind = objective.behind
    assert behind is not None and 0 < behind.numel() < len(objective.completion)
    assert torch.isin(behind, objective.completion.cells).all()
    trainer.start_stage_2()
    with torch.no_grad():
        field.density.fill_(-3.0)  # nearly transparent: every ray crosses the whole body
    reached = torch.zeros(field.color.shape[:-1], dtype=torch.bool).reshape(-1)
    for _ in range(6):
        field.color.grad = None
        objective.backward(objective.total(objective.input_patch()))
        grad = field.color.grad.reshape(-1, 3).abs().sum(1)
        assert grad[behind].max() == 0
        reached |= (grad > 0).cpu()
    assert reached.any()
    field.color.grad = None  # the completion's term does reach them
    terms = objective.regularisers(2, 0)
    objective.backward(objective.total(terms))
    assert field.color.grad.reshape(-1, 3)[behind].abs().sum() > 0


def test_the_far_side_gets_a_layer_of_clothing_that_starts_opaque(tmp_path, tiny_subject):
    """The cells within ``far_side_layer`` outside the body, off the head and behind the body in the photo (the
    camera in front), start stage 2 opaque and are spared the sparsity prior; with the key at 0 there are none."""
    cfg = make_config("cpu-fast", None, TINY + ["far_side_layer=0.03"])
    trainer = Trainer(tiny_subject, cfg, tmp_path / "run")
    field, layer = trainer.avatar.field, trainer.objective.far_side
    sdf = trainer.avatar.body_sdf.reshape(-1)
    assert layer.sum() > 20
    assert (sdf[layer] > 0).all() and (sdf[layer] <= 0.03).all()
    body = tiny_subject.body
    canon = body.pose(body.canonical_pose()).vertices
    points = grid_points(field.box.double().cpu(), field.shape).reshape(-1, 3).numpy()[layer]
    owner = np.linalg.norm(points[:, None] - canon[None, ::7], axis=-1).argmin(1) * 7
    parts = body.vertex_parts()
    assert not (parts[owner] == PART_NAMES.index("head")).any()
    torso = parts[owner] == PART_NAMES.index("torso")
    assert torso.sum() > 5
    torso_centre = canon[parts == PART_NAMES.index("torso"), 2].mean()
    assert (points[torso, 2] < torso_centre).all()  # the back, not the chest
    assert trainer.objective.outside_body.reshape(-1)[torch.as_tensor(layer)].sum() == 0
    before = field.density.detach().reshape(-1)[torch.as_tensor(layer)].clone()
    trainer.start_stage_2()
    after = field.density.detach().reshape(-1)[torch.as_tensor(layer)]
    assert (after >= 3.0).all() and (before < 3.0).any()
    off = Trainer(tiny_subject, make_config("cpu-fast", None, TINY + ["far_side_layer=0"]), tmp_path / "off")
    assert not off.objective.far_side.any()


def test_a_fit_trains_when_the_caller_turned_gradients_off(tmp_path, tiny_subject):
    """A script that renders under ``torch.set_grad_enabled(False)`` may still fit (bench_texture_export's demo)."""
    cfg = make_config("cpu-fast", None, TINY + ["init_steps=3", "steps=3"])
    trainer = Trainer(tiny_subject, cfg, tmp_path / "run")
    before = trainer.avatar.field.color.detach().clone()
    with torch.no_grad():
        trainer.run()
    assert (trainer.avatar.field.color.detach() - before).abs().max() > 0
    assert (tmp_path / "run" / "avatar.safetensors").is_file()


@pytest.mark.slow
def test_kill_and_resume(tmp_path, tiny_subject):
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "elicit_diffrender.apps.cli", "fit", str(tiny_subject.root), "--out", str(run)]
    cmd += [x for kv in TINY + ["steps=400"] for x in ("--set", kv)]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 300
    step = 0
    while time.time() < deadline and proc.poll() is None:
        if (run / CHECKPOINT).is_file():
            try:
                data = read_checkpoint(run)
                if data["stage"] == 2 and data["step"] >= 20:
                    step = data["step"]
                    break
            except Exception:  # caught mid-rename on a slow disk; try again
                pass
        time.sleep(0.5)
    assert step >= 20, "no stage-2 checkpoint appeared"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (run / "avatar.safetensors").exists()
    # A second start without --resume refuses to overwrite; with it, it continues from the checkpoint and
    # removes what a kill in the middle of a checkpoint save leaves.
    again = subprocess.run(cmd, env=env, capture_output=True, text=True)
    assert again.returncode == 2 and "--resume" in again.stderr
    stale = run / f".{CHECKPOINT}.k1ll3d.safetensors"
    stale.write_bytes((run / CHECKPOINT).read_bytes()[:1000])
    safetensors_temp = run / ".tmpAb12Cd"  # what safetensors itself leaves when killed while writing
    safetensors_temp.write_bytes(b"\0" * 1000)
    done = subprocess.run(cmd + ["--resume"], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    log = (run / "log.txt").read_text()
    resumed = [line for line in log.splitlines() if "resumed from" in line]
    assert resumed and int(resumed[-1].rsplit("step", 1)[1]) >= step
    report = json.loads((run / "run.json").read_text())
    assert report["encoder"]["kind"] == "mirror" and "weights-free fallback" in report["encoder"]["name"]
    assert "mirror" in report["final_losses"]["stage2"] and "semantic" not in report["final_losses"]["stage2"]
    assert (run / "avatar.safetensors").is_file() and not stale.exists() and not safetensors_temp.exists()
