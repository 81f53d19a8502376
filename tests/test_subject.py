"""The elicit-subject/1 format: round trips and one clear error per bad field."""

import json
import shutil

import numpy as np
import pytest

from elicit_diffrender.data.motions import builtin_motion
from elicit_diffrender.data.rigs import ring_cameras
from elicit_diffrender.data.subject import SubjectError, load_subject, write_subject


@pytest.fixture(scope="module")
def subject_dir(tmp_path_factory, anny_body):
    root = tmp_path_factory.mktemp("subject") / "s"
    cams = {c.name: c for c in ring_cameras(n=3, width=40, height=30)}
    motion = builtin_motion("wave", anny_body, n_frames=4)
    rng = np.random.default_rng(0)
    views = {(c, f): (rng.random((30, 40, 3)), rng.random((30, 40)) > 0.5) for c in cams for f in (0, 2)}
    write_subject(root, {"model": "anny", "phenotype": {"height": 0.6}}, cams, motion, "cam01", 2, views)
    return root


def test_round_trip(subject_dir):
    s = load_subject(subject_dir)
    assert s.input_camera == "cam01" and s.input_frame == 2 and s.input_index == 2
    assert sorted(s.views()) == sorted((c, f) for c in ("cam00", "cam01", "cam02") for f in (0, 2))
    img = s.image("cam00", 0)
    assert img.shape == (30, 40, 3) and 0 <= img.min() and img.max() <= 1
    assert s.mask("cam02", 2).dtype == bool
    np.testing.assert_allclose(s.cameras["cam01"].K, ring_cameras(n=3, width=40, height=30)[1].K)


def edit(subject_dir, tmp_path, fn):
    root = tmp_path / "bad"
    shutil.copytree(subject_dir, root)
    fn(root)
    return root


def _json_edit(name, change):
    def fn(root):
        data = json.loads((root / name).read_text())
        change(data)
        (root / name).write_text(json.dumps(data))

    return fn


BAD_CASES = {
    "missing subject.json": (lambda r: (r / "subject.json").unlink(), "subject.json: file not found"),
    "bad json": (lambda r: (r / "cameras.json").write_text("{"), "not valid JSON"),
    "format": (_json_edit("subject.json", lambda d: d.update(format="elicit-subject/0")), "field 'format'"),
    "unknown camera": (
        _json_edit("subject.json", lambda d: d["input"].update(camera="cam99")),
        "unknown camera 'cam99'",
    ),
    "unknown frame": (_json_edit("subject.json", lambda d: d["input"].update(frame=7)), "'input.frame'"),
    "camera K shape": (
        _json_edit("cameras.json", lambda d: d["cam00"].update(K=[[1, 0], [0, 1]])),
        "camera 'cam00' field 'K' must be \\(3, 3\\), got \\(2, 2\\)",
    ),
    "camera R": (
        _json_edit("cameras.json", lambda d: d["cam00"].update(R=[[2, 0, 0], [0, 1, 0], [0, 0, 1]])),
        "not a rotation",
    ),
    "camera width": (_json_edit("cameras.json", lambda d: d["cam00"].update(width=-4)), "'width'"),
    "missing image": (lambda r: (r / "images" / "cam01" / "000002.png").unlink(), "image not found"),
    "nan pose": (
        lambda r: np.savez(
            r / "motion.npz",
            pose=np.full((4, 104, 3), np.nan, np.float32),
            global_orient=np.zeros((4, 3)),
            transl=np.zeros((4, 3)),
        ),
        "'pose' contains NaN",
    ),
    "wrong joints": (
        lambda r: np.savez(
            r / "motion.npz",
            pose=np.zeros((4, 24, 3), np.float32),
            global_orient=np.zeros((4, 3)),
            transl=np.zeros((4, 3)),
        ),
        "24 joints",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_subjects_name_file_and_field(subject_dir, tmp_path, case):
    fn, message = BAD_CASES[case]
    with pytest.raises(SubjectError, match=message):
        load_subject(edit(subject_dir, tmp_path, fn))


def test_mask_size_must_match_the_image(subject_dir, tmp_path):
    from elicit_diffrender.core.io import write_image

    root = edit(
        subject_dir, tmp_path, lambda r: write_image(r / "masks" / "cam01" / "000002.png", np.zeros((10, 10), np.uint8))
    )
    with pytest.raises(SubjectError, match="mask is 10x10, expected 40x30"):
        load_subject(root)
