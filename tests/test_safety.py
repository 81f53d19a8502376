"""Opening a file never runs code: crafted pickles in every user file are refused with one line."""

import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from elicit_diffrender.body import BodyModelError, load_body
from elicit_diffrender.core.io import write_image
from elicit_diffrender.core.safe_load import UnsafeFileError, load_npy, load_pickle
from elicit_diffrender.data.motions import MotionError, load_motion, load_motion_npz
from elicit_diffrender.model.avatar import AvatarError
from elicit_diffrender.model.load import load_avatar

PACKAGE = Path(__file__).resolve().parents[1] / "elicit_diffrender"


class Payload:
    """Unpickling this runs ``touch MARKER``: what a crafted file would do."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def elicit(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "elicit_diffrender.apps.cli", *args], capture_output=True, text=True)


def assert_refused(done: subprocess.CompletedProcess, marker: Path, text: str = "refused") -> None:
    last = done.stderr.strip().splitlines()[-1]
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert last.startswith("elicit ") and ": error: " in last and text in last, last
    assert not marker.exists(), "the payload ran"


@pytest.fixture
def marker(tmp_path):
    return tmp_path / "PWNED"


def write_photo(folder: Path, size: int = 64) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rgba = np.concatenate([np.full((size, size, 3), 0.5), np.ones((size, size, 1))], 2)
    write_image(folder / "gt_image.png", rgba)
    mask = np.zeros((size, size), np.uint8)
    mask[10:50, 20:40] = 255
    write_image(folder / "gt_mask.png", mask)


def test_resume_from_a_crafted_checkpoint(tmp_path, marker):
    from test_fit import TINY  # noqa: I001 - the tiny fit settings are shared with the fit tests

    from elicit_diffrender.inputs.synth import synthesize

    subject = synthesize(9, tmp_path / "s", size=48, spp=1, n_cameras=2, texture_size=64)
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoint.safetensors").write_bytes(pickle.dumps({"x": Payload(marker)}))
    sets = [x for kv in TINY for x in ("--set", kv)]
    assert_refused(elicit("fit", str(subject), "--out", str(run), "--resume", *sets), marker, "cannot resume")


def test_prepare_params_with_a_payload(tmp_path, marker):
    write_photo(tmp_path / "photo")
    np.savez(tmp_path / "evil.npz", focal_l=np.float32(500), pred_joints=np.array([Payload(marker)], dtype=object))
    done = elicit(
        "prepare", str(tmp_path / "photo" / "gt_image.png"), "--params", str(tmp_path / "evil.npz"), "--out",
        str(tmp_path / "out"),
    )  # fmt: skip
    assert_refused(done, marker)
    assert not (tmp_path / "out").exists()


def test_import_wild_params_with_a_payload(tmp_path, marker):
    write_photo(tmp_path / "src")
    np.savez(
        tmp_path / "src" / "gt_params.npz",
        pose=np.array([Payload(marker)], dtype=object),
        shape=np.zeros(10),
        global_t=np.zeros(3),
        focal_l=np.float32(500),
    )
    assert_refused(elicit("import", "elicit-wild", str(tmp_path / "src"), "--out", str(tmp_path / "out")), marker)


def test_import_zju_annots_with_a_payload(tmp_path, marker):
    src = tmp_path / "zju"
    src.mkdir()
    np.save(src / "annots.npy", np.array({"cams": Payload(marker), "ims": []}, dtype=object), allow_pickle=True)
    done = elicit("import", "zju", str(src), "--out", str(tmp_path / "out"), "--frames", "0")
    assert_refused(done, marker)


def test_zju_motion_folder_with_a_payload(tmp_path, marker, smpl_file, anny_body):
    params = tmp_path / "new_params"
    params.mkdir()
    np.save(params / "0.npy", np.array({"poses": Payload(marker)}, dtype=object), allow_pickle=True)
    with pytest.raises(MotionError, match="SMPL joints"):  # an Anny avatar never opens them
        load_motion(params, anny_body)
    with pytest.raises(MotionError, match="refused: it asks to run"):
        load_motion(params, load_body({"model": "smpl", "model_path": str(smpl_file)}))
    assert not marker.exists()


def test_motion_npz_smpl_model_and_avatar_with_payloads(tmp_path, marker):
    pose = np.array([Payload(marker)], dtype=object)
    np.savez(tmp_path / "m.npz", pose=pose, global_orient=np.zeros((1, 3)), transl=np.zeros((1, 3)))
    with pytest.raises(MotionError, match="refused: field 'pose' holds pickled"):
        load_motion_npz(tmp_path / "m.npz")
    with open(tmp_path / "SMPL_NEUTRAL.pkl", "wb") as f:
        pickle.dump({"v_template": np.zeros((3, 3)), "f": Payload(marker)}, f, protocol=2)
    with pytest.raises(BodyModelError, match="refused: it asks to run posix.system"):
        load_body({"model": "smpl", "model_path": str(tmp_path / "SMPL_NEUTRAL.pkl")})
    torch.save({"format": "elicit-avatar/1", "tensors": Payload(marker)}, tmp_path / "avatar.pt")
    with pytest.raises(AvatarError, match="unreadable avatar file") as err:
        load_avatar(tmp_path / "avatar.pt")
    assert "weights_only" not in str(err.value)  # never the advice to load it unsafely
    assert not marker.exists()


def test_restricted_unpickler_reads_arrays_dicts_and_sparse_matrices(tmp_path):
    import scipy.sparse as sp

    data = {"K": [np.eye(3)], "name": "cam", "n": np.float32(2.5), "J": sp.csc_matrix(np.eye(4)), "t": (1, 2.0)}
    with open(tmp_path / "ok.pkl", "wb") as f:
        pickle.dump(data, f, protocol=2)
    back = load_pickle(tmp_path / "ok.pkl")
    assert back["name"] == "cam" and back["n"] == 2.5 and back["J"].toarray().trace() == 4
    np.save(tmp_path / "ok.npy", np.array(data, dtype=object), allow_pickle=True)
    assert load_npy(tmp_path / "ok.npy")["t"] == (1, 2.0)
    np.save(tmp_path / "plain.npy", np.arange(3))
    assert load_npy(tmp_path / "plain.npy").tolist() == [0, 1, 2]
    (tmp_path / "junk.npy").write_bytes(b"junk")
    with pytest.raises(UnsafeFileError, match="not a readable .npy"):
        load_npy(tmp_path / "junk.npy")


def test_no_unsafe_loading_anywhere_in_the_package():
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text()
        for unsafe in ("allow_pickle=" + "True", "weights_only=" + "False", "pickle.load(", "pickle.loads("):
            assert unsafe not in text, f"{path}: {unsafe}"
