"""Run MediaPipe Pose on one image; executed by the MediaPipe environment's own Python.

    python mediapipe_runner.py IMAGE OUT.npz

Writes ``landmarks`` (33, 3): x, y in pixels and visibility, ``world`` (33, 3): MediaPipe's metric
landmarks (metres, origin between the hips, axes of the camera: x right, y down, z away),
``segmentation`` (H, W) in [0, 1] (the one person Pose tracks) and ``people`` (H, W) in [0, 1]
(selfie segmentation: everyone in the photo).
Kept free of this package's imports: MediaPipe 0.10.21 pins numpy<2 and lives in its own environment.
The legacy ``solutions`` API with model_complexity=1 uses models bundled in the wheel (no download).
"""

import sys

import mediapipe as mp
import numpy as np
from PIL import Image


def main(image_path: str, out_path: str) -> int:
    image = np.asarray(Image.open(image_path).convert("RGB"))
    h, w = image.shape[:2]
    with mp.solutions.selfie_segmentation.SelfieSegmentation(model_selection=0) as selfie:
        people = np.asarray(selfie.process(image).segmentation_mask, dtype=np.float32)
    with mp.solutions.pose.Pose(static_image_mode=True, model_complexity=1, enable_segmentation=True) as pose:
        result = pose.process(image)
    if result.pose_landmarks is None:
        empty = np.zeros((0, 3))
        np.savez(out_path, landmarks=empty, world=empty, segmentation=np.zeros((h, w), np.float32), people=people)
        return 0
    lm = np.array([[p.x * w, p.y * h, p.visibility] for p in result.pose_landmarks.landmark], dtype=np.float64)
    world = np.array([[p.x, p.y, p.z] for p in result.pose_world_landmarks.landmark], dtype=np.float64)
    segmentation = np.asarray(result.segmentation_mask, dtype=np.float32)
    np.savez(out_path, landmarks=lm, world=world, segmentation=segmentation, people=people)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
