"""``scripts/bench_prepare.py``'s true-body IoU: what a perfect body scores against a mask that holds clothes."""

import importlib.util
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "bench_prepare.py"
spec = importlib.util.spec_from_file_location("bench_prepare", SCRIPT)
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)


def test_a_clothed_mask_scores_the_true_body_below_one_and_its_own_outline_at_one(tiny_subject, tmp_path):
    from elicit_diffrender.data.mesh_render import MeshRenderer
    from elicit_diffrender.data.subject import load_subject

    clothed = bench.true_body_iou(tiny_subject.root)
    assert 0.5 < clothed < 0.97  # the synthetic garments stand off the body

    root = tmp_path / "subject"
    shutil.copytree(tiny_subject.root, root)
    subject = load_subject(root)
    camera, frame = subject.input_camera, subject.input_frame
    posed = subject.body.pose(*subject.motion.frame(subject.input_index))
    outline = MeshRenderer(subject.body.faces).render(posed.vertices, [subject.cameras[camera]], ("mask",))["mask"][0]
    Image.fromarray(np.where(outline > 0, 255, 0).astype(np.uint8)).save(subject.mask_path(camera, frame))
    assert bench.true_body_iou(root) > 0.999
