"""Importers: ELICIT's in-the-wild layout (both focal variants, SMPL or Anny) and ZJU-MoCap."""

import numpy as np
import pytest

from elicit_diffrender.body.fitting import SMPL_TO_ANNY
from elicit_diffrender.core.io import write_image
from elicit_diffrender.data.subject import load_subject
from elicit_diffrender.inputs.importers import SourceImportError, import_elicit_wild, import_zju


def write_wild(folder, focal, pred_joints=None, size=64):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    rgba = np.concatenate([rng.random((size, size, 3)), np.ones((size, size, 1))], 2)
    write_image(folder / "gt_image.png", rgba)
    mask = np.zeros((size, size), np.uint8)
    mask[10:50, 20:40] = 255
    write_image(folder / "gt_mask.png", mask)
    params = {
        "pose": 0.1 * rng.standard_normal((1, 72)).astype(np.float32),
        "shape": np.zeros((1, 10), np.float32),
        "global_t": np.array([[0.0, 0.2, 9.0]], np.float32),
        "focal_l": focal,
    }
    if pred_joints is not None:
        params["pred_joints"] = pred_joints
    np.savez(folder / "gt_params.npz", **params)


def test_wild_with_smpl_files_both_focal_variants(tmp_path, smpl_file):
    for k, focal in enumerate((np.int64(5000), np.array([1448.15], np.float32))):
        src = tmp_path / f"src{k}"
        write_wild(src, focal)
        s = load_subject(import_elicit_wild(src, tmp_path / f"out{k}", smpl_path=str(smpl_file)))
        cam = s.cameras["input"]
        assert cam.K[0, 0] == pytest.approx(float(np.ravel(focal)[0]), rel=1e-6)
        assert cam.K[0, 2] == 32 and np.allclose(cam.R, np.eye(3)) and np.allclose(cam.T, 0)
        assert s.body_spec["model"] == "smpl" and s.motion.pose.shape[1] == 24
        assert s.mask("input", 0).sum() == 40 * 20
        # The input frame is the CLIFF fit: pelvis near global_t, the body upside down in camera space.
        posed = s.body.pose(*s.motion.frame(0))
        assert posed.vertices[:, 2].mean() == pytest.approx(9.0, abs=0.3)


def test_wild_without_smpl_fits_anny_to_pred_joints(tmp_path, anny_body, monkeypatch):
    monkeypatch.delenv("ELICIT_SMPL_DIR", raising=False)
    # Target joints: Anny's own joints for a posed body, flipped into camera space 3 m away.
    pose = anny_body.zero_pose()
    anny_body.set_semantic(pose, "l_elbow", (-0.6, 0, 0))
    posed = anny_body.pose(pose, np.array([np.pi, 0, 0]), np.array([0.1, 0.0, 3.0]))
    joints = np.zeros((1, 45, 3), np.float32)
    for smpl_id, name in SMPL_TO_ANNY.items():
        joints[0, smpl_id] = posed.bone_transforms[anny_body.joint_index(name), :3, 3]
    write_wild(tmp_path / "src", np.array([1448.15], np.float32), joints)
    s = load_subject(import_elicit_wild(tmp_path / "src", tmp_path / "out"))
    assert s.body_spec["model"] == "anny"
    assert s.meta["import"]["joint_error_mm"] < 15
    frames = s.body.pose(*s.motion.frame(5)).bone_transforms
    head = frames[s.body.joint_index("head"), :3, 3]
    pelvis = frames[s.body.joint_index("root"), :3, 3]
    assert head[1] < pelvis[1] - 0.3  # the motion is placed upright in camera space (image up is -y)


def test_wild_errors_name_file_and_field(tmp_path, monkeypatch):
    monkeypatch.delenv("ELICIT_SMPL_DIR", raising=False)
    write_wild(tmp_path / "a", np.int64(5000))
    with pytest.raises(SourceImportError, match="no 'pred_joints'"):
        import_elicit_wild(tmp_path / "a", tmp_path / "o")
    with pytest.raises(SourceImportError, match="gt_image.png: image not found"):
        (tmp_path / "b").mkdir()
        import_elicit_wild(tmp_path / "b", tmp_path / "o")
    write_wild(tmp_path / "c", np.int64(5000))
    np.savez(tmp_path / "c" / "gt_params.npz", pose=np.zeros((1, 72)), shape=np.zeros((1, 10)), focal_l=5000)
    with pytest.raises(SourceImportError, match="missing field 'global_t'"):
        import_elicit_wild(tmp_path / "c", tmp_path / "o")


def test_zju_layout(tmp_path, smpl_file):
    src = tmp_path / "zju"
    rng = np.random.default_rng(1)
    cams = {"K": [], "R": [], "T": [], "D": []}
    ims = []
    frames = [0, 1]
    for _ in range(2):
        cams["K"].append(np.array([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]]))
        cams["R"].append(np.eye(3))
        cams["T"].append(np.array([[0.0], [0.0], [3000.0]]))
        cams["D"].append(np.zeros(5))
    for f in frames:
        ims.append({"ims": [f"Camera_B{c + 1}/{f:06d}.jpg" for c in range(2)]})
        for c in range(2):
            write_image(src / f"Camera_B{c + 1}" / f"{f:06d}.png", rng.random((24, 32, 3)))
            (src / f"Camera_B{c + 1}" / f"{f:06d}.png").rename(src / f"Camera_B{c + 1}" / f"{f:06d}.jpg")
            write_image(src / "mask_cihp" / f"Camera_B{c + 1}" / f"{f:06d}.png", (rng.random((24, 32)) > 0.5) * 1.0)
    np.save(src / "annots.npy", {"cams": cams, "ims": ims}, allow_pickle=True)
    (src / "new_params").mkdir()
    for f in frames:
        np.save(
            src / "new_params" / f"{f}.npy",
            {
                "poses": 0.1 * rng.standard_normal((1, 72)),
                "Rh": np.zeros((1, 3)),
                "Th": np.zeros((1, 3)),
                "shapes": np.zeros((1, 10)),
            },
        )
    s = load_subject(import_zju(src, tmp_path / "out", frames, input_camera=1, smpl_path=str(smpl_file)))
    assert s.input_camera == "cam01" and sorted(s.views()) == [("cam00", 0), ("cam00", 1), ("cam01", 0), ("cam01", 1)]
    np.testing.assert_allclose(s.cameras["cam00"].T, [0, 0, 3.0])  # millimetres -> metres
