"""The command line: clear one-line errors and the render command on a fitted run."""

import subprocess
import sys

import numpy as np
import pytest

from elicit_diffrender.apps.cli import main


def test_bad_subject_gives_one_line_and_exit_2(tmp_path, capsys):
    (tmp_path / "s").mkdir()
    assert main(["fit", str(tmp_path / "s"), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "subject.json: file not found" in err and "Traceback" not in err
    assert main(["fit", str(tmp_path / "s"), "--out", str(tmp_path / "r"), "--set", "bogus=1"]) == 2
    assert "unknown config key 'bogus'" in capsys.readouterr().err


@pytest.mark.slow
def test_render_and_eval_commands(tmp_path):
    from test_fit import TINY  # noqa: I001 - the tiny fit settings are shared with the fit tests

    from elicit_diffrender.inputs.synth import synthesize

    subject = synthesize(7, tmp_path / "s", size=64, spp=2, n_cameras=3, texture_size=128)
    run = tmp_path / "run"
    fast = [x for kv in TINY + ["init_steps=10", "steps=10"] for x in ("--set", kv)]
    assert main(["fit", str(subject), "--out", str(run), *fast]) == 0
    assert (
        main(
            [
                "render",
                str(run),
                "--motion",
                "wave",
                "--cameras",
                "orbit",
                "--out",
                str(tmp_path / "v.gif"),
                "--size",
                "48",
                "--samples",
                "16",
            ]
        )
        == 0
    )
    assert (tmp_path / "v.gif").is_file() and (tmp_path / "v_contact.png").is_file()
    import imageio.v2 as imageio

    frames = imageio.mimread(tmp_path / "v.gif")
    assert len(frames) == 60 and np.asarray(frames[0]).shape[:2] == (48, 48)
    assert (
        main(
            [
                "render",
                str(run),
                "--cameras",
                str(subject),
                "--out",
                str(tmp_path / "frames"),
                "--size",
                "32",
                "--samples",
                "8",
            ]
        )
        == 0
    )
    assert len(list((tmp_path / "frames").glob("*.png"))) > 3
    assert main(["eval", str(run), str(subject), "--out", str(tmp_path / "m.json"), "--max-views", "2"]) == 0
    import json

    m = json.loads((tmp_path / "m.json").read_text())
    assert m["novel_view"]["views"] == 2 and m["novel_view"]["psnr"] > 5 and m["novel_view"]["lpips"] is None
    assert m["encoder"] == "mirror completion (weights-free fallback)" and m["lpips_reason"]
    solid = {"silhouette_iou", "hole_fraction", "spill"}
    assert set(m["novel_view"]["rear"]) == {"degrees", "views", "psnr", "ssim", "lpips"} | solid
    assert set(m["novel_view"]["side"]) == set(m["novel_view"]["rear"]) and solid <= set(m["novel_view"])
    assert all(0.0 <= m["novel_view"][k] <= 1.0 for k in ("silhouette_iou", "hole_fraction"))
    # Aligned to itself (the photo path's evaluation): the identity, and the same novel-view images.
    aligned = tmp_path / "aligned.json"
    assert main(["eval", str(run), str(subject), "--out", str(aligned), "--max-views", "2", "--align"]) == 0
    a = json.loads(aligned.read_text())
    assert abs(a["alignment"]["scale"] - 1) < 1e-6 and a["alignment"]["vertex_error_m"]["max"] < 1e-6
    assert "novel_pose" not in a and abs(a["novel_view"]["psnr"] - m["novel_view"]["psnr"]) < 1e-3


@pytest.mark.parametrize("args", [["--help"], ["fit", "--help"]])
def test_help(args):
    done = subprocess.run([sys.executable, "-m", "elicit_diffrender.apps.cli", *args], capture_output=True, text=True)
    assert done.returncode == 0 and "usage" in done.stdout
