"""The mirror completion (weights-free semantic prior): visibility, the photo's light, sources, and a term that moves
only unseen cells, relit."""

import numpy as np
import torch
from scipy.spatial import cKDTree

from elicit_diffrender.body import PART_NAMES
from elicit_diffrender.body.template import vertex_normals
from elicit_diffrender.core.cameras import look_at
from elicit_diffrender.data.mesh_render import MeshAppearance, MeshRenderer
from elicit_diffrender.fit.completion import (
    FRONT_STRIP,
    MirrorCompletion,
    behind_body,
    exit_depth,
    facing_cosine,
    visible_vertices,
)
from elicit_diffrender.fit.shading import RATIOS, Shading, _search, estimate_shading, fibonacci_sphere
from elicit_diffrender.model.field import CanonicalField, grid_points, signed_distance


def _canonical(anny_body):
    canon = anny_body.pose(anny_body.canonical_pose())
    return canon.vertices, vertex_normals(canon.vertices, anny_body.faces)


def _field_around(verts, normals, voxel=0.03):
    """A colour grid 10 cm round the body, and the body's signed distance on it."""
    box = torch.tensor(np.stack([verts.min(0) - 0.1, verts.max(0) + 0.1]), dtype=torch.float32)
    field = CanonicalField(box, voxel)
    return field, field.body_distance(verts, normals)


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


def test_points_on_the_far_side_of_the_body_are_behind_it_thick_or_thin(anny_body):
    """Seen from the front, points just inside the front of the torso or the neck are not behind the body; points
    just inside their backs are, the neck's though it is thin; points above the head are not."""
    verts, normals = _canonical(anny_body)
    centre = verts.mean(0)
    cam = look_at(centre + np.array([0.0, 0.0, 3.0]), centre, np.array([0.0, 1.0, 0.0]), 300.0, 256, 256)
    depth = MeshRenderer(anny_body.faces).render(verts, [cam], ("depth",))["depth"][0]
    far = exit_depth(verts, cam, depth)
    hit = depth > 0
    assert (far[hit] >= depth[hit]).all() and (far[~hit] == 0).all()
    parts = anny_body.vertex_parts()
    torso = (parts == PART_NAMES.index("torso")) & (np.abs(verts[:, 0] - centre[0]) < 0.05)
    head = parts == PART_NAMES.index("head")
    neck_y = verts[head, 1].min() - 0.03  # below the jaw, above the shoulders
    neck = torso & (np.abs(verts[:, 1] - neck_y) < 0.015)
    chest = torso & (np.abs(verts[:, 1] - (neck_y - 0.25)) < 0.02)
    for part in (chest, neck):
        front = part & (normals[:, 2] > 0.7)
        back = part & (normals[:, 2] < -0.7)
        assert front.sum() >= 3 and back.sum() >= 3
        assert not behind_body(verts[front] - 0.01 * normals[front], cam, depth, far).any()
        assert behind_body(verts[back] - 0.01 * normals[back], cam, depth, far).all()
    above = verts[chest] + np.array([0.0, verts[:, 1].max() - verts[chest, 1].min() + 0.1, 0.0])
    assert not behind_body(above, cam, depth, far).any()


SNAPPED = 0.06  # metres a moved image may shift onto the surface: up to the cells' margin (0.05) plus a vertex spacing


def test_unseen_cells_take_the_colour_of_their_mirror_image(anny_body):
    verts, normals = _canonical(anny_body)
    parts = anny_body.vertex_parts()
    centre_z = np.array([verts[parts == k, 2].mean() for k in range(len(PART_NAMES))])
    seen = verts[:, 2] > centre_z[parts]  # the front half of every part
    box = torch.tensor(np.stack([verts.min(0) - 0.1, verts.max(0) + 0.1]), dtype=torch.float32)
    field = CanonicalField(box, 0.04)
    sdf = field.body_distance(verts, normals)
    pairs = MirrorCompletion.build(field, verts, normals, parts, seen, sdf, margin=0.05, rule="mirror")
    assert len(pairs) == pairs.unseen > 0  # every part has seen vertices, so every unseen cell has a source
    assert sum(pairs.rule_counts.values()) == len(pairs) and pairs.rule_counts["nearest seen"] == 0
    assert torch.equal(pairs.gains, torch.ones(len(pairs)))  # no light given: nothing is relit
    cells = grid_points(field.box.double(), field.shape).reshape(-1, 3).numpy()[pairs.cells.numpy()]
    src = pairs.sources.numpy()
    head = PART_NAMES.index("head")
    _, nearest = cKDTree(verts).query(cells)
    # Front/back mirror images: same x and y, and the source is in front of the cell; a torso cell near the midline
    # takes the point beside the front's middle (a tie, a placket, a V-neck), on its own side, never the middle,
    # moved onto the body's surface there (so its x and y are the image's within SNAPPED).
    mid = verts[:, 0].mean()
    off = cells[:, 0] - mid
    in_strip = (parts[nearest] == PART_NAMES.index("torso")) & (np.abs(off) < FRONT_STRIP)
    beside = np.abs(src[:, 0] - (mid + np.where(off >= 0, 1.0, -1.0) * FRONT_STRIP)) < SNAPPED
    beside &= np.abs(src[:, 1] - cells[:, 1]) < SNAPPED
    same_xy = (np.abs(src[:, 0] - cells[:, 0]) < 1e-6) & (np.abs(src[:, 1] - cells[:, 1]) < 1e-6)
    front_back = np.where(in_strip, beside, same_xy)
    assert front_back[parts[nearest] != head].mean() > 0.8
    behind = cells[:, 2] < centre_z[parts[nearest]]  # (an unseen cell in front, between the legs, mirrors back)
    assert (src[front_back & behind, 2] > cells[front_back & behind, 2]).all() and (front_back & behind).mean() > 0.5
    assert in_strip.sum() > 20 and front_back[in_strip].mean() > 0.8
    # Every moved image is found within SNAPPED of its place; a few images of other rules fall there too.
    moved_count, found = pairs.rule_counts["front/back beside the midline"], (front_back & in_strip).sum()
    assert 0.95 * found <= moved_count <= found
    # The image moved sideways lies as high above the body's surface as its cell (the plain image of a cell on the
    # back's middle, moved to the strip's edge, lies in the air in front of the chest).
    height = signed_distance(cells, verts, normals)
    moved = front_back & in_strip
    assert np.percentile(np.abs(signed_distance(src, verts, normals) - height)[moved], 90) < 0.01
    # The head is never mirrored front to back (its back is not a face): its cells copy a seen vertex of its crown.
    assert not (front_back & (parts[nearest] == head) & (np.abs(src[:, 2] - cells[:, 2]) > 1e-6)).any()
    assert pairs.rule_counts["crown"] > 0
    head_src = cKDTree(verts).query(src[parts[nearest] == head])
    assert (head_src[0] < 1e-6).all() and (parts[head_src[1]] == head).all() and seen[head_src[1]].all()
    assert (normals[head_src[1], 1] > 0.5).all()
    # The crown is the top of the head: the up-facing brows, nose and lips below it (seen here) are the face.
    top = verts[parts == head, 1].max()
    face_up = seen & (parts == head) & (normals[:, 1] > 0.5) & (verts[:, 1] < top - 0.09)
    assert face_up.sum() > 20 and (verts[head_src[1], 1] > top - 0.07).all()

    # Front red, back blue (per part): the term pulls the back towards red and never touches the front.
    all_cells = grid_points(field.box.double(), field.shape).reshape(-1, 3).numpy()
    _, owner = cKDTree(verts).query(all_cells)
    front = torch.as_tensor(all_cells[:, 2] > centre_z[parts[owner]]).reshape(field.shape)
    with torch.no_grad():
        field.color[..., 0] = torch.where(front, 3.0, -3.0)
        field.color[..., 2] = torch.where(front, -3.0, 3.0)
    before = field.color.detach().clone()
    opt = torch.optim.Adam([field.color], lr=0.2)
    first = float(pairs.loss(field, 0, field.color.reshape(-1, 3)[pairs.cells]).detach())
    for step in range(60):
        loss = pairs.loss(field, step, field.color.reshape(-1, 3)[pairs.cells])
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(pairs.loss(field, 60, field.color.reshape(-1, 3)[pairs.cells]).detach()) < 0.2 * first
    changed = (field.color.detach() - before).abs().sum(-1).reshape(-1) > 0
    assert changed.any() and not changed[~torch.isin(torch.arange(changed.numel()), pairs.cells)].any()
    moved = torch.sigmoid(field.color.detach().reshape(-1, 3)[pairs.cells])
    _, src_owner = cKDTree(verts).query(src)
    deep = torch.as_tensor(src[:, 2] - centre_z[parts[src_owner]] > 2 * field.voxel_size)  # well inside the red
    assert deep.sum() > 100 and (moved[deep, 0] > 0.5).float().mean() > 0.9  # the back turned red


def _lit_body(anny_body, light: Shading, size: int = 384, pattern: float = 0.0):
    """A front view of the posed body whose colour is a per-part albedo times ``light`` at its normals; ``pattern``:
    the standard deviation of a per-vertex log-normal factor on the albedo (a print, folds, stains)."""
    body = anny_body.pose(anny_body.zero_pose())
    verts, normals = body.vertices, vertex_normals(body.vertices, anny_body.faces)
    rng = np.random.default_rng(3)
    albedo = rng.uniform(0.25, 0.8, (len(PART_NAMES), 3))[anny_body.vertex_parts()]
    albedo = albedo * np.exp(rng.normal(0.0, pattern, (len(verts), 1))) if pattern else albedo
    colors = np.clip(albedo * light(normals)[:, None] / (1 + light.ratio), 0.0, 1.0)
    centre = verts.mean(0)
    cam = look_at(centre + np.array([0.0, 0.0, 3.0]), centre, np.array([0.0, 1.0, 0.0]), 420.0, size, size)
    renderer = MeshRenderer(anny_body.faces, MeshAppearance(vertex_colors=colors))
    out = renderer.render(verts, [cam], ("color", "depth"), spp=4)
    depth = out["depth"][0]
    seen = visible_vertices(verts, normals, cam, depth, depth > 0)
    return out["color"][0], depth > 0, cam, verts, normals, seen


def test_the_photos_light_is_recovered_from_the_body_it_shows(anny_body):
    truth = Shading(np.array([0.4, 0.7, 0.6]) / np.linalg.norm([0.4, 0.7, 0.6]), 1.0)
    image, person, cam, verts, normals, seen = _lit_body(anny_body, truth)
    est = estimate_shading(image, person, cam, verts, normals, seen)
    assert np.degrees(np.arccos(np.clip(est.direction @ truth.direction, -1, 1))) < 12.0
    assert 0.6 < est.ratio < 1.5
    # Under flat light there is nothing to find.
    flat = estimate_shading(*_lit_body(anny_body, Shading(truth.direction, 0.0)))
    assert flat.ratio < 0.1
    # A heavily patterned albedo hides most of the light's effect: the light explains 15% of the brightness
    # within the albedo groups (the subjects lit by one key light explain 11-40%) and is still found.
    patterned = estimate_shading(*_lit_body(anny_body, truth, pattern=0.7))
    assert 0.1 < patterned.explained < 0.2 and patterned.ratio > 0.2
    assert np.degrees(np.arccos(np.clip(patterned.direction @ truth.direction, -1, 1))) < 12.0


def test_the_light_search_finds_the_least_squares_of_every_candidate():
    """``_search``'s closed-form cost (no (N, D) residuals) picks the ratio and direction whose residuals, each
    minus its cluster's weighted mean, have the least weighted squares, computed here the direct way."""
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    group = rng.integers(0, 5, 500)
    light = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])
    log_y = rng.normal(size=5)[group] + np.log1p(0.9 * np.maximum(normals @ light, 0)) + 0.05 * rng.normal(size=500)
    weight = (rng.random(500) > 0.2).astype(float)
    dirs = fibonacci_sphere(60)
    cost, ratio, d, residuals = _search(log_y, normals, group, weight, dirs)
    onehot = np.eye(5)[group] * weight[:, None]
    best = (np.inf, None, None, None)
    for k in RATIOS:
        r = log_y[:, None] - np.log1p(k * np.maximum(normals @ dirs.T, 0.0))
        res = r - ((onehot.T @ r) / np.maximum(onehot.sum(0), 1e-9)[:, None])[group]
        costs = (weight[:, None] * res**2).sum(0)
        if costs.min() < best[0]:
            best = (costs.min(), k, int(costs.argmin()), res[:, costs.argmin()])
    assert (ratio, d) == (best[1], best[2])
    np.testing.assert_allclose(cost, best[0], rtol=1e-9)
    np.testing.assert_allclose(residuals, best[3], atol=1e-12)


def test_unseen_cells_facing_away_from_the_light_are_relit_darker(anny_body):
    verts, normals = _canonical(anny_body)
    parts = anny_body.vertex_parts()
    centre_z = np.array([verts[parts == k, 2].mean() for k in range(len(PART_NAMES))])
    seen = verts[:, 2] > centre_z[parts]
    light = Shading(np.array([0.0, 0.0, 1.0]), 1.0)  # from the front
    box = torch.tensor(np.stack([verts.min(0) - 0.1, verts.max(0) + 0.1]), dtype=torch.float32)
    field = CanonicalField(box, 0.04)
    with torch.no_grad():
        field.color.fill_(1.0)  # everything sigmoid(1) = 0.73 grey
    pairs = MirrorCompletion.build(
        field, verts, normals, parts, seen, field.body_distance(verts, normals), 0.05, light(normals), rule="mirror"
    )
    target = pairs.targets(field)
    cells = grid_points(field.box.double(), field.shape).reshape(-1, 3).numpy()[pairs.cells.numpy()]
    _, owner = cKDTree(verts).query(cells)
    back = normals[owner, 2] < -0.5
    assert back.sum() > 50
    # A back cell copies a front source lit 1 + cos, so its target is darker by that factor.
    assert (pairs.gains[torch.as_tensor(back)] < 0.8).float().mean() > 0.9
    assert torch.allclose(target, (torch.sigmoid(torch.tensor(1.0)) * pairs.gains[:, None]).clamp(max=1.0), atol=1e-6)


def test_the_blurred_target_is_the_mean_of_seven_trilinear_lookups(anny_body):
    """The targets' sparse blur matrix reads the colour grid as trilinear look-ups at each source and six points
    ``BLUR_VOXELS`` cells around it do, border-clamped where they leave the box."""
    from elicit_diffrender.fit.completion import BLUR_VOXELS
    from elicit_diffrender.model.avatar import sample_grid

    verts, normals = _canonical(anny_body)
    parts = anny_body.vertex_parts()
    centre_z = np.array([verts[parts == k, 2].mean() for k in range(len(PART_NAMES))])
    box = torch.tensor(np.stack([verts.min(0) - 0.06, verts.max(0) + 0.06]), dtype=torch.float32)
    field = CanonicalField(box, 0.04)
    with torch.no_grad():
        field.color.copy_(torch.randn(field.color.shape, generator=torch.Generator().manual_seed(0)))
    pairs = MirrorCompletion.build(
        field,
        verts,
        normals,
        parts,
        verts[:, 2] > centre_z[parts],
        field.body_distance(verts, normals),
        margin=0.05,
        rule="mirror",
    )
    step = BLUR_VOXELS * field.voxel_size
    offsets = [torch.zeros(3)] + [sign * step * torch.eye(3)[k] for k in range(3) for sign in (1.0, -1.0)]
    grid = field.color.detach().permute(3, 0, 1, 2)
    logits = torch.stack([sample_grid(grid, field.box, pairs.sources + o) for o in offsets]).mean(0)
    assert (pairs.sources + step > box[1]).any() or (pairs.sources - step < box[0]).any()  # the border is met
    torch.testing.assert_close(pairs.targets(field), torch.sigmoid(logits).clamp(0, 1), atol=2e-5, rtol=0)


def test_the_guarded_rule_keeps_front_details_in_front_and_gives_the_back_of_the_head_hair(anny_body):
    """The guarded mirror: a back cell whose mirror source shows a front-only detail (a band of pockets down one
    side of the chest, beside the middle that the mirror never copies) takes what its band mostly shows instead;
    other cells keep their mirror source; behind the ears the head takes the hair the photo shows round the face,
    and a bald head (skin all round) takes none."""
    from elicit_diffrender.fit.completion import head_layout

    verts, normals = _canonical(anny_body)
    parts = anny_body.vertex_parts()
    torso, head = parts == PART_NAMES.index("torso"), parts == PART_NAMES.index("head")
    facing = normals[:, 2]  # a camera far in front
    seen = facing > 0.0
    mid = verts[torso, 0].mean()
    ear_y, ear_z, _ = head_layout(verts, parts)
    top, detail_color = (0.2, 0.3, 0.8), (0.9, 0.1, 0.1)
    skin, hair = (0.8, 0.6, 0.5), (0.1, 0.08, 0.05)
    colors = np.tile(top, (len(verts), 1))
    side = verts[:, 0] - mid
    detail = torso & (side > FRONT_STRIP) & (side < FRONT_STRIP + 0.05) & (verts[:, 1] > 0.1)  # collar to belt
    colors[detail] = detail_color
    colors[head] = skin
    colors[head & ((verts[:, 1] > ear_y + 0.03) | (verts[:, 2] < ear_z))] = hair
    colors[~seen] = np.nan
    field, sdf = _field_around(verts, normals)

    def build(colors):
        return MirrorCompletion.build(
            field, verts, normals, parts, seen, sdf, 0.05, colors=colors, facing=facing, rule="guarded"
        )

    pairs = build(colors)
    assert len(pairs) == pairs.unseen > 0 and pairs.rule_counts["hair"] > 0
    cells = grid_points(field.box.double(), field.shape).reshape(-1, 3).numpy()[pairs.cells.numpy()]
    _, owner = cKDTree(verts).query(cells)
    _, source_vertex = cKDTree(verts).query(pairs.sources.numpy())
    fixed = pairs.colors.numpy()
    back = torso[owner] & (normals[owner, 2] < -0.5)
    onto_detail = back & detail[source_vertex] & (cells[:, 1] > 0.12) & (cells[:, 1] < 0.4)  # below the shoulders
    assert onto_detail.sum() > 10 and pairs.rule_counts["front detail: band colour"] >= onto_detail.sum()
    np.testing.assert_allclose(fixed[onto_detail], np.tile(top, (onto_detail.sum(), 1)), atol=1e-6)  # not the detail
    plain = back & ~detail[source_vertex] & (cells[:, 0] - mid < -0.1) & (cells[:, 1] > 0.12) & (cells[:, 1] < 0.4)
    assert plain.sum() > 20 and np.isnan(fixed[plain]).all()  # a source that agrees with its band stays live
    scalp_back = head[owner] & (cells[:, 2] < ear_z - 0.02) & (cells[:, 1] > ear_y)
    assert scalp_back.sum() > 5
    np.testing.assert_allclose(fixed[scalp_back], np.tile(hair, (scalp_back.sum(), 1)), atol=1e-6)
    target = pairs.targets(field).numpy()  # fixed colours where given, the grid's mirrored colour elsewhere
    np.testing.assert_allclose(target[onto_detail], fixed[onto_detail], atol=1e-6)
    colors[head & seen] = skin
    bald = build(colors)
    assert bald.rule_counts["hair"] == 0


def _holding(anny_body, gap: float):
    """The canonical body with both forearms moved to lie across the chest, ``gap`` metres in front of it."""
    verts, normals = _canonical(anny_body)
    parts = anny_body.vertex_parts()
    torso = parts == PART_NAMES.index("torso")
    chest_y = np.percentile(verts[torso, 1], 70)
    front = verts[torso & (np.abs(verts[:, 1] - chest_y) < 0.03), 2].max()
    held = verts.copy()
    for name, side in (("left_forearm", 1.0), ("right_forearm", -1.0)):
        arm = parts == PART_NAMES.index(name)
        centre = verts[arm].mean(0)
        held[arm] = verts[arm] - centre + [verts[torso, 0].mean() + 0.06 * side, chest_y, front + gap + 0.05]
    return held, normals, parts, torso, chest_y


def test_seen_torso_behind_forearms_held_in_front_is_no_source(anny_body):
    """Forearms held out in front of the chest may hold a folder: the seen torso between and around them is no
    mirror source, and the back cells that would copy it take the colour their band shows elsewhere; forearms
    resting on the body hold nothing."""
    from elicit_diffrender.fit.completion import HELD_REACH, within_held_reach

    verts, normals, parts, torso, chest_y = _holding(anny_body, 0.15)
    centre = verts[torso].mean(0)
    cam = look_at(centre + np.array([0.0, 0.0, 3.0]), centre, np.array([0.0, 1.0, 0.0]), 300.0, 256, 256)
    seen = normals[:, 2] > 0.0
    held = within_held_reach(verts, parts, facing_cosine(verts, normals, cam), cam, seen)
    chest = torso & seen & (np.abs(verts[:, 1] - chest_y) < 0.03) & (np.abs(verts[:, 0] - centre[0]) < 0.05)
    hips = torso & seen & (verts[:, 1] < chest_y - 0.1 - 2 * HELD_REACH)
    assert chest.sum() > 10 and held[chest].all()
    assert hips.sum() > 10 and not held[hips].any()
    assert not held[~torso].any() and not held[~seen].any()
    resting, *_ = _holding(anny_body, 0.0)
    assert not within_held_reach(resting, parts, facing_cosine(resting, normals, cam), cam, seen).any()

    # A folder in the held zone, a blue top elsewhere: the back no longer copies the folder.
    top, folder = (0.2, 0.3, 0.8), (0.8, 0.8, 0.7)
    canon, _ = _canonical(anny_body)
    colors = np.tile(top, (len(verts), 1))
    colors[held] = folder
    colors[~seen] = np.nan
    field, sdf = _field_around(canon, normals)

    def build(held):
        return MirrorCompletion.build(
            field, canon, normals, parts, seen, sdf, 0.05, colors=colors, facing=normals[:, 2], held=held
        )

    plain, guarded = build(None), build(held)
    assert "held in front: band colour" not in plain.rule_counts and plain.colors is None
    assert torch.equal(plain.cells, guarded.cells)
    _, plain_source = cKDTree(canon).query(plain.sources.numpy())
    copies_folder = held[plain_source]
    assert copies_folder.sum() > 10 and guarded.rule_counts["held in front: band colour"] == copies_folder.sum()
    fixed = guarded.colors.numpy()
    np.testing.assert_allclose(fixed[copies_folder], np.tile(top, (copies_folder.sum(), 1)), atol=1e-6)
    assert np.isnan(fixed[~copies_folder]).all()  # every other cell keeps its mirror source
    _, source = cKDTree(canon).query(guarded.sources.numpy())
    assert not held[source].any()


def test_the_pull_on_a_saturated_cell_does_not_vanish():
    """A cell on the far side of the sigmoid from its target (colour 0.98 against 0.02) is pulled at least as hard as
    a mid-tone cell 0.1 from its target. Through the sigmoid its gradient was 40x weaker, and the grid's smoothness
    (on logits) blurred the unseen side's garment borders: a top faded into dark trousers at the waist."""
    target = torch.tensor([[0.02, 0.02, 0.02], [0.6, 0.6, 0.6]])
    pairs = MirrorCompletion(torch.arange(2), torch.zeros(2, 3), torch.ones(2), {}, 2, target, True)
    logits = torch.tensor([[4.0, 4.0, 4.0], [float(torch.logit(torch.tensor(0.5)))] * 3], requires_grad=True)
    pairs.loss(None, 0, logits).backward()
    saturated, mid_tone = logits.grad.abs().sum(1)
    assert saturated > mid_tone > 0, logits.grad
    assert torch.allclose(pairs.targets(None), target)


def test_hull_cells_beyond_the_margin_are_completed_and_no_other_far_cell(anny_body):
    """Cells farther from the body than the margin are completed only where the room's hull holds them (hair, a
    garment between the legs): each such cell finds its nearest vertex, however far out; no other cell changes."""
    verts, normals = _canonical(anny_body)
    parts = anny_body.vertex_parts()
    field, sdf = _field_around(verts, normals, voxel=0.04)
    seen = verts[:, 2] > np.median(verts[:, 2])
    margin = 0.03
    points = grid_points(field.box.double(), field.shape).reshape(-1, 3).numpy()
    dist, owner = cKDTree(verts).query(points)
    hull = np.zeros(sdf.size, dtype=bool)
    behind = points[:, 2] < np.median(verts[:, 2])
    far_behind = np.flatnonzero((dist > 0.06) & (dist < 0.09) & behind & (sdf.reshape(-1) > margin))
    hull[far_behind[::5]] = True  # some cells well beyond the margin, behind the body (unseen)
    plain = MirrorCompletion.build(field, verts, normals, parts, seen, sdf, margin=margin, rule="mirror")
    held = MirrorCompletion.build(field, verts, normals, parts, seen, sdf, margin=margin, hull=hull, rule="mirror")
    completed, far = set(held.cells.tolist()), np.flatnonzero(hull)
    hidden = far[~seen[owner[far]]]  # the hull cells whose nearest vertex is unseen
    assert len(hidden) > 10 and held.unseen - plain.unseen == len(hidden)  # each found its owner, however far out
    assert len(completed & set(hidden)) > 10  # and most a source
    assert completed - set(far) == set(plain.cells.tolist())  # no other cell changes
    outside = plain.cells.numpy()[sdf.reshape(-1)[plain.cells.numpy()] > 0]
    assert dist[outside].max() < margin  # without a hull no cell outside the body lies beyond the margin
