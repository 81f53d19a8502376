"""Shared fixtures: the Anny body (cached per session), small synthetic SMPL-format model files, and the fit
tests' tiny synthetic subject (one per test module)."""

import pickle

import numpy as np
import pytest

from elicit_diffrender.body.smpl_model import SMPL_JOINTS
from elicit_diffrender.data.subject import load_subject
from elicit_diffrender.inputs.synth import synthesize

# A T-pose skeleton in SMPL's joint order (metres, +y up, facing +z).
SMPL_SKELETON = np.array([
    [0.0, 0.0, 0.0], [0.09, -0.08, 0.0], [-0.09, -0.08, 0.0], [0.0, 0.1, 0.0], [0.1, -0.48, 0.0],
    [-0.1, -0.48, 0.0], [0.0, 0.22, 0.0], [0.1, -0.88, 0.0], [-0.1, -0.88, 0.0], [0.0, 0.32, 0.0],
    [0.1, -0.92, 0.12], [-0.1, -0.92, 0.12], [0.0, 0.48, 0.0], [0.08, 0.42, 0.0], [-0.08, 0.42, 0.0],
    [0.0, 0.6, 0.0], [0.18, 0.42, 0.0], [-0.18, 0.42, 0.0], [0.45, 0.42, 0.0], [-0.45, 0.42, 0.0],
    [0.7, 0.42, 0.0], [-0.7, 0.42, 0.0], [0.78, 0.42, 0.0], [-0.78, 0.42, 0.0],
])  # fmt: skip
SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]


def make_smpl_file(path, n_betas: int = 10) -> dict:
    """Write a tiny SMPL-format pickle: a 4 cm cube at every joint, rigidly skinned to it."""
    cube = np.array([[x, y, z] for x in (-0.02, 0.02) for y in (-0.02, 0.02) for z in (-0.02, 0.02)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    verts = np.concatenate([j + cube for j in SMPL_SKELETON])
    faces = np.concatenate([tris + 8 * k for k in range(24)])
    n = verts.shape[0]
    weights = np.zeros((n, 24))
    weights[np.arange(n), np.arange(n) // 8] = 1.0
    regressor = np.zeros((24, n))
    regressor[np.arange(n) // 8, np.arange(n)] = 1.0 / 8
    rng = np.random.default_rng(0)
    shapedirs = 0.01 * rng.standard_normal((n, 3, n_betas))
    data = {
        "v_template": verts,
        "f": faces.astype(np.int64),
        "weights": weights,
        "J_regressor": regressor,
        "shapedirs": shapedirs,
        "posedirs": np.zeros((n, 3, 207)),
        "kintree_table": np.array([[4294967295 if p < 0 else p for p in SMPL_PARENTS], list(range(24))]),
        "joint_names": SMPL_JOINTS,
    }
    with open(path, "wb") as f:
        pickle.dump(data, f)
    return data


@pytest.fixture(scope="session")
def smpl_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("smpl") / "SMPL_NEUTRAL.pkl"
    make_smpl_file(path)
    return path


@pytest.fixture(scope="session")
def anny_body():
    from elicit_diffrender.body import load_body

    return load_body({"model": "anny"})


@pytest.fixture(scope="module")
def tiny_subject(tmp_path_factory):
    """A small synthetic subject (seed 5, 96 px, 4 cameras) for the fit tests' tiny fits."""
    root = synthesize(5, tmp_path_factory.mktemp("fit") / "s", size=96, spp=4, n_cameras=4, texture_size=256)
    return load_subject(root)
