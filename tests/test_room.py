"""Room for what the photo shows beyond the body: grown from the input mask, only where the mask is."""

import shutil

import numpy as np
import pytest
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from elicit_diffrender.body import PART_NAMES
from elicit_diffrender.core.io import write_image
from elicit_diffrender.data.subject import load_subject
from elicit_diffrender.fit.room import LEG_PARTS, MAX_REACH, SLACK, InputFrame, input_room
from elicit_diffrender.inputs.synth import synthesize
from elicit_diffrender.model.avatar import Avatar, sample_grid

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
    assert room.extends is None and room.hull is None and room.widest == MARGIN


def test_a_skirt_gets_depth_in_front_of_and_behind_the_legs(tmp_path):
    """Seed 1 wears a flared skirt: the mask bridges the gap between its legs down to the hem, so the room
    grows over a hull as deep as the skirt is wide, between the hips and the hem only."""
    skirt = load_subject(synthesize(1, tmp_path / "skirt", size=192, spp=4, n_cameras=4, texture_size=256))
    room = input_room(skirt, MARGIN)
    assert room.hull is not None and 0.12 < room.hull_reach <= MAX_REACH
    body = skirt.body
    canon, parts = body.pose(body.canonical_pose()).vertices, body.vertex_parts()
    thighs = canon[np.isin(parts, [PART_NAMES.index(n) for n in ("left_thigh", "right_thigh")])]
    mid = thighs.mean(0)  # between the thighs, half way down them
    chest = canon[parts == PART_NAMES.index("torso")].mean(0)
    shins = canon[np.isin(parts, [PART_NAMES.index(n) for n in ("left_shin", "right_shin")])].mean(0)
    ahead = np.array([0.0, 0.0, 0.12])
    points = np.stack([mid + ahead, mid - ahead, chest + 2 * ahead, shins + ahead])
    assert room.hull(points).tolist() == [True, True, False, False]
    assert room(points[:2]).min() >= room.hull_reach
    assert input_room(skirt, MARGIN, garment=False).hull is None


def test_touching_thighs_are_not_a_skirt(subjects, tmp_path):
    """Trousers whose thighs touch below the crotch bridge a narrow gap between the body's legs: no garment.
    The same mask bridging the legs down to where they stand 10 cm apart does make one."""
    plain, _ = subjects
    frame = InputFrame.load(plain)
    legs = [np.isin(frame.labels, side) for side in LEG_PARTS]
    metres_per_pixel = float(np.median(frame.camera.project(frame.posed)[1])) / frame.camera.K[0, 0]
    found = {}
    for limit in (0.04, 0.10):
        copy = tmp_path / f"bridged_{limit}"
        shutil.copytree(plain.root, copy)
        subject = load_subject(copy)
        mask = subject.mask(subject.input_camera, subject.input_frame).copy()
        assert mask.shape == frame.person.shape  # the test subject's mask is at the work size
        for v in np.nonzero(legs[0].any(1) & legs[1].any(1))[0]:
            (_, a1), (b0, _) = sorted((c.min(), c.max()) for c in (np.nonzero(leg[v])[0] for leg in legs))
            if 3 <= b0 - a1 and (b0 - a1 - 1) * metres_per_pixel <= limit:
                mask[v, a1 : b0 + 1] = True
        write_image(subject.mask_path(subject.input_camera, subject.input_frame), mask.astype(np.float32))
        found[limit] = input_room(subject, MARGIN).hull is not None
    assert found == {0.04: False, 0.10: True}


def test_hair_round_the_head_stands_off_its_back_too(subjects, tmp_path):
    """A mask that stands ``STANDOFF`` off the head's outline above the ears (hair round the head) gives the
    room a hull that deep all round the hair-covered head, the back included, which the photo does not show;
    not in front of the face, and not further out. The plain mask's head gets none."""
    plain, _ = subjects
    frame = InputFrame.load(plain)
    assert frame.person.shape == frame.labels.shape  # the test subject's mask is at the work size
    assert "hair" not in input_room(plain, MARGIN).hull_names
    metres_per_pixel = float(np.median(frame.camera.project(frame.posed)[1])) / frame.camera.K[0, 0]
    canon = frame.canonical
    head = canon[frame.vertex_parts == PART_NAMES.index("head")]
    ear_row = frame.camera.project(frame.posed[frame.vertex_parts == PART_NAMES.index("head")])[0][:, 1]
    above_ears = np.arange(frame.person.shape[0])[:, None] < np.percentile(ear_row, 60)
    off_head = ndimage.distance_transform_edt(frame.labels != PART_NAMES.index("head")) * metres_per_pixel
    grown = (off_head <= STANDOFF) & above_ears
    copy = tmp_path / "haired"
    shutil.copytree(plain.root, copy)
    haired = load_subject(copy)
    write_image(haired.mask_path(haired.input_camera, haired.input_frame), (frame.person | grown).astype(np.float32))
    room = input_room(haired, MARGIN)
    assert room.hull_names == ("hair",)
    assert abs(room.hull_reach - SLACK - STANDOFF) < 1.5 * metres_per_pixel, room.hull_reach
    centre = head.mean(0)
    back = head[np.argmin(head[:, 2])] + [0.0, 0.0, -0.5 * STANDOFF]  # behind the skull, at eye level or so
    top = head[np.argmax(head[:, 1])] + [0.0, 0.5 * STANDOFF, 0.0]
    face = head[np.argmax(head[:, 2])] + [0.0, 0.0, 0.5 * STANDOFF]
    far_back = head[np.argmin(head[:, 2])] + [0.0, 0.0, -3 * STANDOFF]
    assert back[1] > centre[1] - 0.05
    assert room.hull(np.stack([back, top, face, far_back])).tolist() == [True, True, False, False]
    assert input_room(haired, MARGIN, hair=False).hull is None


STANDOFF = 0.06  # metres of hair round the head in ``test_hair_round_the_head_stands_off_its_back_too``


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


def test_a_room_weight_keeps_the_torso_beside_a_hanging_arm(anny_body):
    """The torso's skin beside a hanging arm warps back to the canonical torso, not into the arm's room (which
    would copy the torso there: a doubled limb in other poses, and a gap on the torso): with the room at a
    third of the body's motion weight, the torso's own bones win. The room still renders: its foreground
    likelihood is scaled back to 1."""
    import math

    from elicit_diffrender.body.template import vertex_normals
    from elicit_diffrender.model.skinning import inverse_lbs

    body = anny_body
    pose = body.zero_pose().copy()
    body.set_semantic(pose, "l_shoulder", (0.0, 0.0, -math.radians(35)))  # arms 35 degrees below Anny's A-pose
    body.set_semantic(pose, "r_shoulder", (0.0, 0.0, math.radians(35)))
    zero = np.zeros(3)
    posed, canon = body.pose(pose, zero, zero).vertices, body.pose(body.canonical_pose()).vertices
    share = body.reduced_weights()
    arm_bones = [i for i, j in enumerate(body.reduced_joints) if any(k in j for k in ("arm", "wrist", "clavicle"))]
    forearm = posed[share[:, [i for i in arm_bones if "upperarm" not in body.reduced_joints[i]]].sum(1) > 0.9]
    trunk = np.flatnonzero(share[:, arm_bones].sum(1) < 0.05)
    gap = np.array([np.linalg.norm(forearm - v, axis=1).min() for v in posed[trunk]])
    normals = vertex_normals(canon, body.faces)
    pick = trunk[gap < 0.08]  # torso and hip skin within 8 cm of a hanging forearm or hand: in the arm's room
    assert len(pick) > 100
    errors, in_room = {}, {}
    for room_share in (1.0, 0.3):
        config = {"warp_sharpness": 4, "warp_gate": 0.1, "room_weight": room_share}
        avatar = Avatar.from_body(body, {"model": "anny"}, 0.03, MARGIN, config=config)
        weights = avatar.motion_weights().detach()
        x_c, _ = inverse_lbs(
            torch.as_tensor(posed[pick], dtype=torch.float32),
            avatar.obs_to_canonical(avatar.bone_transforms(pose, zero, zero)),
            weights,
            avatar.motion_weights.box,
            sharpness=avatar.sharpness,
            gate=avatar.gate,
        )
        errors[room_share] = float(np.median(np.linalg.norm(x_c.numpy() - canon[pick], axis=1)))
        outside = torch.as_tensor(canon[pick] + 0.05 * normals[pick], dtype=torch.float32)
        in_room[room_share] = float(sample_grid(weights, avatar.motion_weights.box, outside).sum(1).median())
        assert min(1.0, in_room[room_share] / avatar.room_weight) > 0.8  # 5 cm out: rendered as foreground
    assert 0.2 < in_room[0.3] / in_room[1.0] < 0.45  # the room's share of the motion weight
    assert errors[0.3] < 0.5 * errors[1.0] and errors[0.3] < 0.03, errors


def test_splatted_weights_blend_the_nearest_vertices_in_every_chunk():
    """:func:`splat_weights` (chunked) equals the inverse-square-distance blend of the k nearest vertices' weights
    written out at once, across chunk borders; rows of weights that sum to 1 stay so."""
    from elicit_diffrender.model.field import SPLAT_CHUNK, splat_weights

    rng = np.random.default_rng(3)
    vertices = rng.normal(size=(500, 3))
    weights = rng.random((500, 6))
    weights /= weights.sum(1, keepdims=True)
    points = rng.normal(size=(2 * SPLAT_CHUNK + 17, 3))
    dist, idx = cKDTree(vertices).query(points, k=8)
    w = 1.0 / np.maximum(dist, 1e-3) ** 2
    expected = np.einsum("pk,pkb->pb", w, weights[idx]) / w.sum(1, keepdims=True)
    out = splat_weights(points, vertices, weights)
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out.sum(1), 1.0, rtol=1e-12)
