"""Room for what the photo shows beyond the body: grown from the input mask, only where the mask is."""

import shutil

import numpy as np
import pytest
import torch

from elicit_diffrender.avatar import Avatar, sample_grid
from elicit_diffrender.fit.room import input_room
from elicit_diffrender.io import write_image
from elicit_diffrender.subject import load_subject
from elicit_diffrender.synth import synthesize

MARGIN = 0.10
HAIR = 0.20  # metres of mask above the head


@pytest.fixture(scope="module")
def subjects(tmp_path_factory):
    """A small synthetic subject, and a copy whose input mask has ``HAIR`` metres of hair on top of the head."""
    root = tmp_path_factory.mktemp("room")
    plain = load_subject(synthesize(7, root / "plain", size=128, spp=4, n_cameras=4, texture_size=256))
    shutil.copytree(plain.root, root / "hair")
    hair = load_subject(root / "hair")
    cam = hair.cameras[hair.input_camera]
    posed = hair.body.pose(*hair.motion.frame(hair.input_index)).vertices
    top = posed[posed[:, 1].argmax()]
    uv, z = cam.project(top[None])
    (u, v), z = uv[0], z[0]
    px = cam.K[0, 0] / z  # pixels per metre at the head
    mask = hair.mask(hair.input_camera, hair.input_frame).copy()
    mask[max(0, int(v - HAIR * px)) : int(v) + 2, int(u - 0.12 * px) : int(u + 0.12 * px)] = True
    write_image(hair.mask_path(hair.input_camera, hair.input_frame), mask.astype(np.float32))
    return plain, hair


def test_a_mask_like_the_body_keeps_the_margin(subjects):
    plain, _ = subjects
    room = input_room(plain, MARGIN)
    assert room.extends is None and room.widest == MARGIN


def test_hair_above_the_head_grows_the_room_there_only(subjects):
    plain, hair = subjects
    room = input_room(hair, MARGIN)
    assert HAIR - 0.04 < room.reach < HAIR + 0.1
    canon = hair.body.pose(hair.body.canonical_pose()).vertices
    top = canon[canon[:, 1].argmax()]
    above = top + np.array([0.0, 0.15, 0.0])
    beside = top + np.array([0.3, 0.0, 0.0])
    assert room.extends(above[None])[0] and not room.extends(beside[None])[0]
    assert room(np.stack([above, beside])).tolist() == [room.reach, MARGIN]

    # The avatar's box and occupancy reach the hair; without it they stop at the margin.
    grown = Avatar.from_body(hair.body, hair.body_spec, 0.03, room, occupancy_cell=0.04, weight_res=32)
    plain_avatar = Avatar.from_body(plain.body, plain.body_spec, 0.03, MARGIN, occupancy_cell=0.04, weight_res=32)
    assert float(grown.field.box[1, 1]) > above[1] > float(plain_avatar.field.box[1, 1])
    occ = grown.field.occupancy
    box = grown.field.box.numpy()
    cell = np.floor((above - box[0]) / (box[1] - box[0]) * (np.array(occ.shape) - 1) + 0.5).astype(int)
    assert occ[tuple(cell)] == 1
    # The foreground likelihood of the motion weights lets density live there.
    probs = torch.softmax(grown.motion_weights.logits, 0)
    fg = 1 - sample_grid(probs[-1:], grown.motion_weights.box, torch.tensor(above[None], dtype=torch.float32))
    assert float(fg.detach()) > 0.9
