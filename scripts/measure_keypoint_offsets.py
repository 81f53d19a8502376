"""Measure where MediaPipe puts joint landmarks relative to Anny's joint heads (``KEYPOINT_OFFSETS``).

On synthetic subjects (``elicit synth``; the default seeds 4-7 are not the benchmarks' subjects) MediaPipe
runs on every 6th frame of the front camera and on the input frame of every camera within 50 degrees of
it. For each landmark in ``KEYPOINT_OFFSETS`` the offset ``o`` in its bone's frame minimises
``sum |project(joint + R_bone o) - landmark|^2`` (linearised at o = 0, a small ridge); left and right are
then averaged with x mirrored. Prints the offsets and the mean 2D error before and after, next to the
values in use. Needs MediaPipe (``scripts/setup.sh``).

    python scripts/measure_keypoint_offsets.py --work runs/keypoint_offsets
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from elicit_diffrender.body.fitting import KEYPOINT_OFFSETS, KEYPOINTS
from elicit_diffrender.core.checks import read_image, read_mask
from elicit_diffrender.core.io import write_image
from elicit_diffrender.data.subject import load_subject
from elicit_diffrender.inputs.mediapipe_bridge import detect_pose
from elicit_diffrender.outputs.evaluate import angle_around_body

SUBJECTS = {4: "walk_in_place", 5: "wave", 6: "squat", 7: "walk_in_place"}  # seed -> motion
MAX_ANGLE = 50.0  # degrees from the front camera
RIDGE = 1e3  # px^2 per m^2


def views(subject) -> list[tuple[str, int]]:
    """(camera, frame) pairs: every 6th frame of cam00, and frame 0 of the cameras near it."""
    centre = subject.body.pose(*subject.motion.frame(0)).vertices.mean(0)
    front, up = subject.cameras["cam00"], np.array([0.0, 1.0, 0.0])
    out = [("cam00", f) for f in range(0, len(subject.motion), 6)]
    for name, cam in subject.cameras.items():
        angle = angle_around_body(cam, front, centre, up)
        if name != "cam00" and angle < MAX_ANGLE and subject.image_path(name, 0).is_file():
            out.append((name, 0))
    return out


def observations(root: Path) -> dict[int, list]:
    """landmark -> [(K, joint in camera space, bone rotation in camera space, MediaPipe's pixel)]."""
    s = load_subject(root)
    body = s.body
    out: dict[int, list] = {k: [] for k in KEYPOINT_OFFSETS}
    for cam_name, frame in views(s):
        cam, posed = s.cameras[cam_name], body.pose(*s.motion.frame(frame))
        rgb, _ = read_image(s.image_path(cam_name, frame), "image")
        mask = read_mask(s.mask_path(cam_name, frame), "mask", rgb.shape[:2])
        with tempfile.TemporaryDirectory() as tmp:
            found = detect_pose(write_image(Path(tmp) / "p.png", np.where(mask[..., None], rgb, 0.5))).landmarks
        if found is None:
            continue
        frames = posed.bone_transforms
        for k, (bone, _) in KEYPOINT_OFFSETS.items():
            if found[k, 2] < 0.8:
                continue
            joint = cam.R @ frames[body.joint_index(KEYPOINTS[k][1]), :3, 3] + cam.T
            out[k].append((cam.K, joint, cam.R @ frames[body.joint_index(bone), :3, :3], found[k, :2]))
    return out


def solve(obs: list) -> tuple[np.ndarray, float, float]:
    """The offset (3,) in metres and the mean 2D error (px) before and after it."""

    def project(K, x):
        u = K @ x
        return u[:2] / u[2]

    rows, rhs = [], []
    for K, x, R, uv in obs:
        fx, fy, z = K[0, 0], K[1, 1], x[2]
        jac = np.array([[fx / z, 0, -fx * x[0] / z**2], [0, fy / z, -fy * x[1] / z**2]])
        rows.append(jac @ R)
        rhs.append(uv - project(K, x))
    A, y = np.concatenate(rows), np.concatenate(rhs)
    offset = np.linalg.solve(A.T @ A + RIDGE * np.eye(3), A.T @ y)
    before = np.mean([np.linalg.norm(uv - project(K, x)) for K, x, _, uv in obs])
    after = np.mean([np.linalg.norm(uv - project(K, x + R @ offset)) for K, x, R, uv in obs])
    return offset, float(before), float(after)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", type=Path, default=Path("runs") / "keypoint_offsets")
    args = p.parse_args()
    elicit = str(Path(sys.executable).with_name("elicit"))
    obs: dict[int, list] = {k: [] for k in KEYPOINT_OFFSETS}
    for seed, motion in SUBJECTS.items():
        root = args.work / f"subject_{seed}"
        if not (root / "subject.json").is_file():
            subprocess.run([elicit, "synth", "--seed", str(seed), "--motion", motion, "--out", str(root)], check=True)
        for k, rows in observations(root).items():
            obs[k] += rows
    mirror = np.array([-1.0, 1.0, 1.0])
    for left in sorted(k for k in KEYPOINT_OFFSETS if k % 2 == 1):
        right = left + 1
        (o_l, b_l, a_l), (o_r, b_r, a_r) = solve(obs[left]), solve(obs[right])
        mean = (o_l + mirror * o_r) / 2
        print(
            f"landmarks {left}/{right} ({KEYPOINT_OFFSETS[left][0]}): left offset {np.round(mean, 3).tolist()} m "
            f"(in use {list(KEYPOINT_OFFSETS[left][1])}); per side {np.round(o_l, 3).tolist()} / "
            f"{np.round(o_r, 3).tolist()}; mean error {(b_l + b_r) / 2:.1f} -> {(a_l + a_r) / 2:.1f} px "
            f"over {len(obs[left]) + len(obs[right])} detections"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
