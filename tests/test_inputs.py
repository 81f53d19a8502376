"""Bad input is one line naming the file or field (exit code 2); legitimate odd input is read right;
folders are written as a whole, so a failed overwrite loses nothing."""

import errno
import json

import numpy as np
import pytest
from PIL import Image

from elicit_diffrender.apps.cli import main
from elicit_diffrender.core.checks import InputError, read_image, read_mask
from elicit_diffrender.core.io import folder_in_place, write_image
from elicit_diffrender.data.motions import MotionError, load_motion_npz
from elicit_diffrender.data.subject import SubjectError, load_subject
from elicit_diffrender.inputs.importers import SourceImportError, import_zju
from elicit_diffrender.inputs.prepare import PrepareError, prepare
from elicit_diffrender.inputs.synth import synthesize


@pytest.fixture(scope="module")
def small_subject(tmp_path_factory):
    return synthesize(4, tmp_path_factory.mktemp("inputs") / "s", size=48, spp=1, n_cameras=2, texture_size=64)


def one_line_error(capsys, code: int, text: str) -> str:
    """Exit code 2 and one error line (after any progress bar, which redraws with carriage returns)."""
    err = capsys.readouterr().err
    lines = [line.split("\r")[-1] for line in err.split("\n") if line.split("\r")[-1].strip()]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert text in lines[0] and ": error: " in lines[0], lines[0]
    return lines[0]


def test_images_and_masks_at_every_bit_depth(tmp_path):
    grey16 = (np.linspace(0, 65535, 64).reshape(8, 8)).astype(np.uint16)
    Image.fromarray(grey16).save(tmp_path / "g16.png")
    rgb, alpha = read_image(tmp_path / "g16.png")
    assert rgb.shape == (8, 8, 3) and alpha is None and rgb.max() == pytest.approx(1.0) and rgb.min() == 0.0
    m = np.zeros((8, 8), bool)
    m[2:6, 3:5] = True
    Image.fromarray(m).convert("1").save(tmp_path / "m1.png")
    Image.fromarray((m * 65535).astype(np.uint16)).save(tmp_path / "m16.png")
    Image.fromarray((m * 255).astype(np.uint8)).convert("RGB").save(tmp_path / "m8rgb.png")
    for name in ("m1.png", "m16.png", "m8rgb.png"):
        np.testing.assert_array_equal(read_mask(tmp_path / name), m, err_msg=name)
    rgba = np.concatenate([np.full((8, 8, 3), 0.25), m[..., None].astype(float)], 2)
    write_image(tmp_path / "rgba.png", rgba)
    rgb, alpha = read_image(tmp_path / "rgba.png")
    assert abs(rgb.mean() - 0.25) < 0.01 and (alpha > 0.5).sum() == m.sum()
    with pytest.raises(InputError, match=r"mask is 8x8, expected 9x8"):
        read_mask(tmp_path / "m1.png", expect_hw=(8, 9))
    with pytest.raises(InputError, match=r"above the 1e-05 MP limit; shrink it, or raise the limit"):
        read_image(tmp_path / "g16.png", max_megapixels=1e-5)
    (tmp_path / "junk.png").write_bytes(b"junk")
    with pytest.raises(InputError, match="unreadable image"):
        read_image(tmp_path / "junk.png")


def copy_subject(src, dst):
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_an_empty_input_mask_and_a_body_far_away_are_refused(small_subject, tmp_path):
    root = copy_subject(small_subject, tmp_path / "empty")
    write_image(root / "masks" / "cam00" / "000000.png", np.zeros((48, 48), np.uint8))
    with pytest.raises(SubjectError, match="the input mask is empty"):
        load_subject(root)
    root = copy_subject(small_subject, tmp_path / "far")
    m = dict(np.load(root / "motion.npz"))
    m["transl"] = m["transl"] + 1e6
    np.savez(root / "motion.npz", **m)
    with pytest.raises(SubjectError, match="'transl' reaches 1e\\+06 m"):
        load_subject(root)


def test_motions_of_strings_or_ragged_values(tmp_path):
    good = dict(pose=np.zeros((2, 104, 3)), global_orient=np.zeros((2, 3)), transl=np.zeros((2, 3)))
    np.savez(tmp_path / "s.npz", **{**good, "pose": np.full((2, 104, 3), "x")})
    with pytest.raises(MotionError, match="field 'pose' must hold numbers"):
        load_motion_npz(tmp_path / "s.npz")
    np.savez(tmp_path / "ids.npz", **good, frame_ids=np.array([0, 0]))
    with pytest.raises(MotionError, match="'frame_ids' must be 2 distinct integers"):
        load_motion_npz(tmp_path / "ids.npz")


def test_command_line_numbers(tmp_path, capsys):
    for args, text in (
        (["render", "r", "--motion", "rest", "--cameras", "orbit", "--out", "o.mp4", "--size", "0"], "--size"),
        (["render", "r", "--motion", "rest", "--cameras", "orbit", "--out", "o.mp4", "--samples", "0"], "--samples"),
        (["render", "r", "--motion", "rest", "--cameras", "orbit", "--out", "o.mp4", "--fps", "0"], "--fps"),
        (["eval", "r", "s", "--out", "m.json", "--scale", "2"], "--scale"),
        (["export", "r", "--out", "a.glb", "--texture-size", "16"], "--texture-size: must be an integer in [64, 8192]"),
        (["prepare", "p.png", "--out", "o", "--focal", "-500"], "--focal: must be a number in [1, 1e+06]"),
        (["synth", "--out", "o", "--size", "-3"], "--size"),
    ):
        with pytest.raises(SystemExit) as done:
            main(args)
        one_line_error(capsys, done.value.code, text)


def test_prepare_params_are_checked(tmp_path, capsys):
    write_image(tmp_path / "p.png", np.full((40, 30, 3), 0.5))
    out = str(tmp_path / "out")
    code = main(["prepare", str(tmp_path / "p.png"), "--out", out, "--params", str(tmp_path / "none.npz")])
    one_line_error(capsys, code, "none.npz: parameter file not found")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    code = main(["prepare", str(tmp_path / "p.png"), "--out", out, "--params", str(tmp_path / "junk.npz")])
    one_line_error(capsys, code, "junk.npz: not a readable .npz file")
    np.savez(tmp_path / "j.npz", pred_joints=np.zeros((1, 5, 3)))
    with pytest.raises(PrepareError, match="'pred_joints' must hold at least 24 3D joints"):
        prepare(tmp_path / "p.png", out, params_path=tmp_path / "j.npz")
    np.savez(tmp_path / "f.npz", focal_l=np.float32(-3))
    with pytest.raises(PrepareError, match="'focal_l' must be one positive number"):
        prepare(tmp_path / "p.png", out, params_path=tmp_path / "f.npz")
    assert not (tmp_path / "out").exists()


def test_malformed_zju_annotations(tmp_path):
    src = tmp_path / "zju"
    src.mkdir()
    cams = {"K": [np.eye(3)], "R": [np.eye(3)], "T": [np.zeros(3)]}
    for annots, text in (
        ({"cams": {"K": [np.eye(3)]}, "ims": []}, "'cams.R' must be a list"),
        ({"cams": {**cams, "K": [np.eye(2)]}, "ims": []}, "field 'K' must be (3, 3)"),
        ({"cams": cams, "ims": [{"ims": [3]}]}, r"'ims\[0\].ims' must list 1 image paths"),
        ({"cams": cams, "ims": [{"ims": ["a.jpg"]}]}, r"frames \[4\] are not in 'ims'"),
    ):
        np.save(src / "annots.npy", np.array(annots, dtype=object), allow_pickle=True)
        with pytest.raises(SourceImportError, match=text.replace("(", r"\(").replace(")", r"\)")):
            import_zju(src, tmp_path / "out", [4])
        assert not (tmp_path / "out").exists()


def test_folders_are_written_whole_and_not_overwritten_unasked(small_subject, tmp_path, capsys, monkeypatch):
    target = copy_subject(small_subject, tmp_path / "subject")
    before = (target / "subject.json").read_text()
    code = main(["synth", "--seed", "4", "--out", str(target), "--size", "48", "--spp", "1"])
    one_line_error(capsys, code, "folder exists and is not empty; pass --force")
    # A full disk halfway through an overwrite: the old subject stays whole and loadable.
    import elicit_diffrender.data.subject as subject_module

    calls = {"n": 0}
    real = subject_module.write_image

    def full_disk(path, image):
        calls["n"] += 1
        if calls["n"] > 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, image)

    monkeypatch.setattr(subject_module, "write_image", full_disk)
    code = main(["synth", "--seed", "4", "--out", str(target), "--size", "48", "--spp", "1", "--force"])
    one_line_error(capsys, code, "No space left on device")
    assert (target / "subject.json").read_text() == before and load_subject(target).motion is not None
    assert [p.name for p in tmp_path.iterdir()] == ["subject"]  # no partial folder left beside it
    # Within a whole-folder write, an error inside the block leaves nothing behind either.
    with pytest.raises(RuntimeError), folder_in_place(tmp_path / "new") as tmp:
        (tmp / "a.txt").write_text("x")
        raise RuntimeError("late failure")
    assert not (tmp_path / "new").exists() and [p.name for p in tmp_path.iterdir()] == ["subject"]


def test_a_run_folder_with_an_earlier_fit_needs_resume_or_force(small_subject, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({}))
    code = main(["fit", str(small_subject), "--out", str(run)])
    one_line_error(capsys, code, "holds an earlier fit (run.json): pass --resume to continue it, --force")


def test_an_unwritable_output_fails_before_the_body_fit(tmp_path, capsys, monkeypatch):
    import elicit_diffrender.core.io as io_module
    import elicit_diffrender.inputs.prepare as prep

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", str(tmp_path / "ro"))

    def no_fit(*args, **kwargs):
        raise AssertionError("the body fit ran before the output folder was checked")

    monkeypatch.setattr(io_module.tempfile, "mkdtemp", read_only)
    monkeypatch.setattr(prep, "person_mask", no_fit)
    write_image(tmp_path / "p.png", np.full((40, 30, 3), 0.5))
    code = main(["prepare", str(tmp_path / "p.png"), "--out", str(tmp_path / "ro" / "subject")])
    one_line_error(capsys, code, "Read-only file system")
