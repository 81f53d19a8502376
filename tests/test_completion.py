"""The mirror completion (weights-free semantic prior): visibility, pairs, and a term that moves only unseen cells."""

import numpy as np
import torch
from scipy.spatial import cKDTree

from elicit_diffrender.body import PART_NAMES
from elicit_diffrender.body.template import vertex_normals
from elicit_diffrender.cameras import look_at
from elicit_diffrender.field import CanonicalField, grid_points
from elicit_diffrender.fit.completion import MirrorCompletion, visible_vertices
from elicit_diffrender.mesh_render import MeshRenderer


def _canonical(anny_body):
    canon = anny_body.pose(anny_body.canonical_pose())
    return canon.vertices, vertex_normals(canon.vertices, anny_body.faces)


def test_visibility_from_a_front_camera_sees_the_front_only(anny_body):
    verts, normals = _canonical(anny_body)
    centre = verts.mean(0)
    cam = look_at(centre + np.array([0.0, 0.0, 3.0]), centre, np.array([0.0, 1.0, 0.0]), 300.0, 256, 256)
    depth = MeshRenderer(anny_body.faces).render(verts, [cam], ("depth",))["depth"][0]
    seen = visible_vertices(verts, normals, cam, depth, depth > 0)
    facing = normals[:, 2]
    torso = anny_body.vertex_parts() == PART_NAMES.index("torso")  # no fingers or ears hiding each other
    assert 0.3 < seen.mean() < 0.7
    assert seen[torso & (facing > 0.5)].mean() > 0.95  # facing the camera
    assert seen[facing < -0.5].mean() < 0.02  # facing away
    # Nothing is seen outside the person's mask.
    assert not visible_vertices(verts, normals, cam, depth, np.zeros_like(depth, dtype=bool)).any()


def test_unseen_cells_take_the_colour_of_their_mirror_image(anny_body):
    verts, normals = _canonical(anny_body)
    parts = anny_body.vertex_parts()
    centre_z = np.array([verts[parts == k, 2].mean() for k in range(len(PART_NAMES))])
    seen = verts[:, 2] > centre_z[parts]  # the front half of every part
    box = torch.tensor(np.stack([verts.min(0) - 0.1, verts.max(0) + 0.1]), dtype=torch.float32)
    field = CanonicalField(box, 0.04)
    pairs = MirrorCompletion.build(field, verts, normals, parts, seen, margin=0.05)
    assert 0 < len(pairs) <= pairs.unseen
    cells = grid_points(field.box.double(), field.shape).reshape(-1, 3).numpy()[pairs.cells.numpy()]
    src = pairs.sources.numpy()
    # Front/back mirror images: same x and y, and the source is in front of the cell.
    front_back = np.abs(src[:, 0] - cells[:, 0]) < 1e-6
    assert front_back.mean() > 0.8
    assert (src[front_back, 2] > cells[front_back, 2]).all()
    # The head is never mirrored front to back (its back is not a face).
    head = PART_NAMES.index("head")
    _, nearest = cKDTree(verts).query(cells)
    assert not (front_back & (parts[nearest] == head) & (np.abs(src[:, 2] - cells[:, 2]) > 1e-6)).any()

    # Front red, back blue (per part): the term pulls the back towards red and never touches the front.
    all_cells = grid_points(field.box.double(), field.shape).reshape(-1, 3).numpy()
    _, owner = cKDTree(verts).query(all_cells)
    front = torch.as_tensor(all_cells[:, 2] > centre_z[parts[owner]]).reshape(field.shape)
    with torch.no_grad():
        field.color[..., 0] = torch.where(front, 3.0, -3.0)
        field.color[..., 2] = torch.where(front, -3.0, 3.0)
    before = field.color.detach().clone()
    opt = torch.optim.Adam([field.color], lr=0.2)
    first = float(pairs.loss(field).detach())
    for _ in range(60):
        loss = pairs.loss(field)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(pairs.loss(field).detach()) < 0.2 * first
    changed = (field.color.detach() - before).abs().sum(-1).reshape(-1) > 0
    assert changed.any() and not changed[~torch.isin(torch.arange(changed.numel()), pairs.cells)].any()
    moved = torch.sigmoid(field.color.detach().reshape(-1, 3)[pairs.cells])
    _, src_owner = cKDTree(verts).query(src)
    deep = torch.as_tensor(src[:, 2] - centre_z[parts[src_owner]] > 2 * field.voxel_size)  # well inside the red
    assert deep.sum() > 100 and (moved[deep, 0] > 0.5).float().mean() > 0.9  # the back turned red
