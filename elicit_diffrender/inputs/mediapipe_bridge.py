"""The boundary to MediaPipe, which lives in its own environment (``mediapipe==0.10.21`` pins numpy<2).

The interpreter is ``ELICIT_MEDIAPIPE_PYTHON``, else ``.venv-mediapipe/bin/python`` beside the
project (``scripts/setup.sh`` creates it), else this interpreter if it can import mediapipe.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import ElicitError

RUNNER = Path(__file__).with_name("mediapipe_runner.py")
INSTALL_HINT = (
    "install it with scripts/setup.sh (it creates .venv-mediapipe with mediapipe==0.10.21), or point "
    "ELICIT_MEDIAPIPE_PYTHON at a Python that has mediapipe 0.10.21"
)


class MediaPipeUnavailable(ElicitError):
    """No Python environment with MediaPipe was found."""


@dataclass
class PoseDetection:
    landmarks: np.ndarray | None  # (33, 3) x, y (pixels), visibility; None when no person was found
    segmentation: np.ndarray  # (H, W) probability of the person Pose tracks
    people: np.ndarray  # (H, W) probability of any person (selfie segmentation)
    world: np.ndarray | None = None  # (33, 3) metric landmarks, camera axes (x right, y down, z away)


def mediapipe_python() -> str | None:
    env = os.environ.get("ELICIT_MEDIAPIPE_PYTHON")
    if env:
        return env
    local = Path(__file__).resolve().parents[2] / ".venv-mediapipe" / "bin" / "python"
    if local.is_file():
        return str(local)
    try:
        import mediapipe  # noqa: F401

        return sys.executable
    except ImportError:
        return None


def detect_pose(image_path: str | Path) -> PoseDetection:
    python = mediapipe_python()
    if python is None:
        raise MediaPipeUnavailable(
            f"MediaPipe is needed for a mask or keypoints here but is not installed: {INSTALL_HINT}"
        )
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "pose.npz"
        try:
            done = subprocess.run([python, str(RUNNER), str(image_path), str(out)], capture_output=True, text=True)
        except OSError as exc:
            raise MediaPipeUnavailable(f"cannot run MediaPipe's Python {python} ({exc}); {INSTALL_HINT}") from None
        if done.returncode != 0 or not out.is_file():
            tail = done.stderr.strip().splitlines()[-1:] or ["(no output)"]
            raise MediaPipeUnavailable(f"MediaPipe failed on {image_path} with {python}: {tail[0]}; {INSTALL_HINT}")
        with np.load(out, allow_pickle=False) as data:
            lm = data["landmarks"]
            world = data["world"] if "world" in data.files else None
            found = lm.shape[0] == 33
            return PoseDetection(
                lm if found else None,
                data["segmentation"],
                data["people"],
                world if found and world is not None and world.shape == (33, 3) else None,
            )
