"""Synthetic clothed subjects: a seeded, textured, clothed Anny person rendered by Mitsuba.

The person is Anny with a seeded phenotype. Garments (shirt, trousers or a skirt, shoes, hair,
skin) are regions of the body surface, each moved out from the body (``garment_offsets``), so the
clothed shape is not the body: tight garments by their thickness along the normals, a loose top by
up to ``LOOSE_TOP`` more towards its hem (a tunic over the hips), a skirt onto a cone that flares
from the waist to its hem above the knees, voluminous hair by up to ``hair_volume`` (a head larger
than Anny's). Garments are painted procedurally in UV space with colours and patterns drawn from the
seed. The back differs from the front (a back print and a higher collar), so completing unseen
areas is measurable. Renders are path-traced under a fixed sky and key light; the subject holds
the input view, the ring at the input frame (novel views) and the input camera over the motion
(novel poses).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..body.anny_model import AnnyBody
from ..body.base import PART_NAMES, BodyModel
from ..body.template import vertex_normals
from ..core.io import folder_in_place, write_image, write_json
from ..data.mesh_render import MeshAppearance, MeshRenderer
from ..data.motions import Motion, builtin_motion
from ..data.rigs import ring_cameras
from ..data.subject import write_subject
from .people import PEOPLE
from .postures import posture

REGIONS = ("skin", "shirt", "collar", "trousers", "shoes", "hair", "skirt")
THICKNESS = {
    "skin": 0.0,
    "shirt": 0.012,
    "collar": 0.014,
    "trousers": 0.016,
    "shoes": 0.018,
    "hair": 0.02,
    "skirt": 0.02,
}
LOOSE_TOP = 0.05  # metres a loose top stands off the body at its hem (on top of its thickness)
SKIRT_FLARE = 0.10  # metres a skirt's radius grows from the waist to its hem
SKIRT_BAND = 0.03  # metres: heights at which a skirt's legs are spread round the cone


@dataclass
class Outfit:
    seed: int
    phenotype: dict
    skin: tuple
    hair: tuple
    hair_long: bool
    shirt: tuple
    shirt_alt: tuple
    shirt_pattern: str
    long_sleeves: bool
    back_print: str
    print_color: tuple
    trousers: tuple
    shorts: bool
    trouser_pattern: str
    shoes: tuple
    loose_top: bool  # a tunic that stands off the body, down over the hips
    skirt: bool  # a flared skirt to above the knees instead of trousers
    hair_volume: float  # metres the hair stands off the head (0: close-cropped)
    # Clothes and postures of the named people (``PEOPLE``); a seed alone draws none of these.
    jacket: tuple | None = None  # a jacket over the top, in this colour (the top's sleeves become the jacket's)
    jacket_open: bool = True  # open: the top shows down the whole front; closed: only a V below the collar
    tie: tuple | None = None  # a tie down the front of the top, in this colour
    front_detail: bool = False  # a logo and a button placket on the front of the top only
    held_object: tuple | None = None  # a folder of this colour held in front of the chest
    hair_down_back: bool = False  # long hair falling onto the upper back
    posture: str = "standing"  # the input photo's posture (``postures.POSTURES``)


def _color(rng: np.random.Generator, lo: float = 0.1, hi: float = 0.95) -> tuple:
    return tuple(float(v) for v in rng.uniform(lo, hi, 3))


def draw_outfit(seed: int) -> Outfit:
    """Everything about the person that the seed decides."""
    rng = np.random.default_rng(seed)
    skins = [(0.93, 0.76, 0.65), (0.80, 0.60, 0.45), (0.62, 0.43, 0.30), (0.42, 0.28, 0.20)]
    hairs = [(0.10, 0.07, 0.05), (0.35, 0.22, 0.12), (0.75, 0.60, 0.35), (0.55, 0.20, 0.10), (0.2, 0.2, 0.22)]
    phenotype = {
        "gender": float(rng.uniform(0.0, 1.0)),
        "age": float(rng.uniform(0.45, 0.65)),
        "muscle": float(rng.uniform(0.3, 0.7)),
        "weight": float(rng.uniform(0.3, 0.7)),
        "height": float(rng.uniform(0.35, 0.75)),
        "proportions": float(rng.uniform(0.4, 0.6)),
    }
    shirt = _color(rng)
    return Outfit(
        seed=seed,
        phenotype=phenotype,
        skin=skins[rng.integers(len(skins))],
        hair=hairs[rng.integers(len(hairs))],
        hair_long=bool(rng.random() < 0.4),
        shirt=shirt,
        shirt_alt=_color(rng),
        shirt_pattern=str(rng.choice(["stripes", "checker", "dots", "solid"])),
        long_sleeves=bool(rng.random() < 0.5),
        back_print=str(rng.choice(["disk", "cross", "band"])),
        print_color=_color(rng),
        trousers=_color(rng, 0.05, 0.6),
        shorts=bool(rng.random() < 0.3),
        trouser_pattern=str(rng.choice(["solid", "denim", "side_stripe"])),
        shoes=_color(rng, 0.05, 0.9),
        loose_top=bool(rng.random() < 0.35),
        skirt=bool(rng.random() < 0.3),
        hair_volume=float(rng.uniform(0.05, 0.14)) if rng.random() < 0.4 else 0.0,
    )


def person_outfit(name: str) -> Outfit:
    """The outfit of a named person (``PEOPLE``)."""
    if name not in PEOPLE:
        raise ValueError(f"unknown person {name!r}; choose from {', '.join(PEOPLE)}")
    seed, changes = PEOPLE[name]
    return replace(draw_outfit(seed), **changes)


def garment_regions(body: AnnyBody, outfit: Outfit) -> np.ndarray:
    """(V,) index into REGIONS for every body vertex, from rest-pose geometry and body parts."""
    v = body.rest_vertices
    parts = body.vertex_parts()
    frames = body.pose(body.zero_pose()).bone_transforms
    joint = {name: frames[body.joint_index(body.semantic[name]), :3, 3] for name in body.semantic}
    part = np.array(PART_NAMES)[parts]
    region = np.zeros(len(v), dtype=np.int64)
    neck_y = joint["neck"][1]
    head_c = joint["head"]
    # Shirt: torso above the waist, upper arms, forearms up to the wrist with long sleeves.
    waist_y = joint["pelvis"][1] + 0.55 * (joint["spine_lower"][1] - joint["pelvis"][1]) + 0.04
    hem_top = waist_y - (0.14 if outfit.loose_top else 0.0)  # a loose top reaches down over the hips
    collar_drop = np.where(v[:, 2] > head_c[2], 0.07, 0.015)  # a V-neck in front, a crew neck behind
    is_torso = part == "torso"
    shirt = is_torso & (v[:, 1] > hem_top) & (v[:, 1] < neck_y - collar_drop)
    for side in ("l", "r"):
        upper = (part == ("left_upper_arm" if side == "l" else "right_upper_arm")) & (v[:, 1] < neck_y - collar_drop)
        fore = part == ("left_forearm" if side == "l" else "right_forearm")
        shoulder, elbow, wrist = joint[f"{side}_shoulder"], joint[f"{side}_elbow"], joint[f"{side}_wrist"]
        along_upper = (v - shoulder) @ (elbow - shoulder) / np.sum((elbow - shoulder) ** 2)
        along_fore = (v - elbow) @ (wrist - elbow) / np.sum((wrist - elbow) ** 2)
        if outfit.long_sleeves:
            shirt |= upper | (fore & (along_fore < 0.9))
        else:
            shirt |= upper & (along_upper < 0.55)
    region[shirt] = REGIONS.index("shirt")
    collar = is_torso & ~shirt & (v[:, 1] > neck_y - collar_drop - 0.025) & (v[:, 1] < neck_y - 0.0)
    region[collar] = REGIONS.index("collar")
    # Trousers: hips and legs down to the ankle (or above the knee for shorts).
    legs = np.isin(part, ["left_thigh", "right_thigh", "left_shin", "right_shin"])
    hem_y = (joint["l_knee"][1] + 0.06) if outfit.shorts else (joint["l_ankle"][1] + 0.06)
    trousers = (is_torso & (v[:, 1] <= waist_y)) | (legs & (v[:, 1] > hem_y))
    region[trousers & ~shirt] = REGIONS.index("trousers")
    if outfit.skirt:
        skirt = ((is_torso & (v[:, 1] <= waist_y)) | legs) & (v[:, 1] > skirt_hem(body, joint)) & ~shirt
        region[skirt] = REGIONS.index("skirt")
        region[legs & (v[:, 1] <= skirt_hem(body, joint))] = REGIONS.index("skin")
    shoes = legs & (v[:, 1] < joint["l_ankle"][1] + 0.035)
    region[shoes] = REGIONS.index("shoes")
    # Hair: the top and back of the head; long hair reaches the neck at the back.
    rel = v - head_c
    is_head = part == "head"
    top = rel[:, 1] > 0.06 - 0.05 * (rel[:, 2] < -0.02)
    back = rel[:, 2] < -0.035
    hair = is_head & (top | (back & (rel[:, 1] > (-0.12 if outfit.hair_long else -0.03))))
    hair &= ~((rel[:, 2] > 0.05) & (rel[:, 1] < 0.09))  # keep the face clear
    if outfit.hair_down_back:  # long hair over the neck's back and the upper back, between the shoulder blades
        reach = (v[:, 1] > neck_y - 0.2) & (v[:, 2] < joint["neck"][2] - 0.02) & (np.abs(v[:, 0]) < 0.13)
        hair |= np.isin(part, ["head", "torso"]) & reach
    region[hair] = REGIONS.index("hair")
    return region


def skirt_hem(body: AnnyBody, joint: dict) -> float:
    """Rest height of a skirt's hem: a hand above the knees."""
    return float(joint["l_knee"][1] + 0.12)


def garment_offsets(body: AnnyBody, outfit: Outfit, region: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(V, 3) rest-pose displacement of every vertex by its garment (see the module's docstring)."""
    v = body.rest_vertices
    thickness = np.array([THICKNESS[r] for r in REGIONS])[region]
    frames = body.pose(body.zero_pose()).bone_transforms
    joint = {name: frames[body.joint_index(body.semantic[name]), :3, 3] for name in body.semantic}
    shirt = region == REGIONS.index("shirt")
    if outfit.loose_top:
        chest_y = joint["spine_upper"][1]
        torso = shirt & (body.vertex_parts() == PART_NAMES.index("torso"))
        drop = np.clip((chest_y - v[:, 1]) / max(chest_y - v[shirt, 1].min(), 1e-6), 0.0, 1.0)
        thickness = thickness + torso * LOOSE_TOP * (0.3 + 0.7 * drop)
    hair = region == REGIONS.index("hair")
    if outfit.hair_volume > 0:
        rel = v - joint["head"]
        away_from_face = np.clip(0.5 - 4.0 * rel[:, 2], 0.3, 1.0)  # fuller at the back than at the hairline
        thickness = thickness + hair * outfit.hair_volume * away_from_face
    offsets = normals * thickness[:, None]
    skirt = region == REGIONS.index("skirt")
    if skirt.any():
        # Onto a cone about the body's vertical axis: the waist's radius, growing by SKIRT_FLARE to the hem. At each
        # height (bands of SKIRT_BAND), each leg's angles about the axis are stretched onto its half of the cone, so
        # that the two meet in front and behind instead of leaving a gap between the legs.
        idx = np.nonzero(skirt)[0]
        axis = joint["pelvis"][[0, 2]]
        radial = v[idx][:, [0, 2]] - axis
        r = np.linalg.norm(radial, axis=1)
        angle = np.arctan2(radial[:, 0], radial[:, 1])  # 0 in front, pi/2 at the body's left (+x)
        parts = np.array(PART_NAMES)[body.vertex_parts()[idx]]
        for side, sign in (("left", 1.0), ("right", -1.0)):
            leg = np.char.startswith(parts, side)
            if leg.sum() < 2:
                continue
            a = np.arctan2(np.maximum(sign * radial[leg, 0], 1e-6), radial[leg, 1])  # from the front, in (0, pi)
            band = np.floor(v[idx[leg], 1] / SKIRT_BAND).astype(int)
            for b in np.unique(band):
                sel = np.nonzero(leg)[0][band == b]
                ab = a[band == b]
                span = max(ab.max() - ab.min(), 1e-6)
                angle[sel] = sign * np.pi * (ab - ab.min()) / span
        waist_y, hem_y = v[idx, 1].max(), skirt_hem(body, joint)
        t = np.clip((waist_y - v[idx, 1]) / max(waist_y - hem_y, 1e-6), 0.0, 1.0)
        cone = np.percentile(r[v[idx, 1] > waist_y - 0.03], 90) + THICKNESS["skirt"] + SKIRT_FLARE * t
        radius = np.maximum(cone, r + THICKNESS["skirt"])
        offsets[idx] = 0.0
        offsets[idx, 0] = axis[0] + radius * np.sin(angle) - v[idx, 0]
        offsets[idx, 2] = axis[1] + radius * np.cos(angle) - v[idx, 2]
    return offsets


def seam_split(faces: np.ndarray, face_uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split vertices along UV seams: (render vertex -> body vertex, render vertex -> uv index) and faces."""
    pairs = np.stack([faces.ravel(), face_uvs.ravel()], 1)
    uniq, inv = np.unique(pairs, axis=0, return_inverse=True)
    return uniq, inv.reshape(-1, 3)


def rasterize_uv(uvs: np.ndarray, faces: np.ndarray, attrs: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric interpolation of per-vertex ``attrs`` (N, C) over the UV layout of ``faces``.

    Texel (row, col) samples uv ((col + 0.5) / size, (row + 0.5) / size), Mitsuba's bitmap layout.
    Returns the (size, size, C) image and a (size, size) coverage mask; uncovered texels are filled
    from the nearest covered one so that bilinear filtering never reads outside the layout.
    """
    out = np.zeros((size, size, attrs.shape[1]), dtype=np.float32)
    covered = np.zeros((size, size), dtype=bool)
    tri_uv = uvs[faces] * size - 0.5  # texel-centre coordinates
    for f in range(faces.shape[0]):
        p = tri_uv[f]
        x0, y0 = np.floor(p.min(0)).astype(int)
        x1, y1 = np.ceil(p.max(0)).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, size - 1), min(y1, size - 1)
        if x1 < x0 or y1 < y0:
            continue
        xs, ys = np.meshgrid(np.arange(x0, x1 + 1), np.arange(y0, y1 + 1))
        pts = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
        a, b, c = p
        m = np.array([[b[0] - a[0], c[0] - a[0]], [b[1] - a[1], c[1] - a[1]]])
        det = np.linalg.det(m)
        if abs(det) < 1e-12:
            continue
        lam = np.linalg.solve(m, (pts - a).T).T
        w = np.concatenate([1 - lam.sum(1, keepdims=True), lam], 1)
        inside = (w >= -1e-3).all(1)
        if not inside.any():
            continue
        w = w[inside]
        px = pts[inside].astype(int)
        out[px[:, 1], px[:, 0]] = w @ attrs[faces[f]]
        covered[px[:, 1], px[:, 0]] = True
    idx = ndimage.distance_transform_edt(~covered, return_distances=False, return_indices=True)
    return out[idx[0], idx[1]], covered


def _stripes(t: np.ndarray, period: float) -> np.ndarray:
    return (np.floor(t / period) % 2).astype(bool)


def paint_texture(
    outfit: Outfit, region: np.ndarray, pos: np.ndarray, normal: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Procedural garment colours per texel from its region, rest position and normal."""
    h, w = region.shape
    tex = np.zeros((h, w, 3), dtype=np.float32)
    x, y, z = pos[..., 0], pos[..., 1], pos[..., 2]
    noise = ndimage.gaussian_filter(rng.standard_normal((h, w)), 1.5)

    def put(mask, color):
        tex[mask] = color

    put(region == REGIONS.index("skin"), outfit.skin)
    shirt = region == REGIONS.index("shirt")
    put(shirt, outfit.shirt)
    if outfit.shirt_pattern == "stripes":
        put(shirt & _stripes(y, 0.05), outfit.shirt_alt)
    elif outfit.shirt_pattern == "checker":
        put(shirt & (_stripes(y, 0.06) ^ _stripes(x + z, 0.06)), outfit.shirt_alt)
    elif outfit.shirt_pattern == "dots":
        put(shirt & ((np.mod(y, 0.07) - 0.035) ** 2 + (np.mod(x + z, 0.07) - 0.035) ** 2 < 0.012**2), outfit.shirt_alt)
    back = shirt & (normal[..., 2] < -0.35) & (np.abs(x) < 0.17)
    if outfit.back_print == "disk":
        put(back & ((x / 0.11) ** 2 + ((y - 0.33) / 0.11) ** 2 < 1), outfit.print_color)
    elif outfit.back_print == "cross":
        put(back & (y > 0.15) & (y < 0.5) & ((np.abs(x) < 0.025) | (np.abs(y - 0.36) < 0.025)), outfit.print_color)
    elif outfit.back_print == "band":
        put(back & (np.abs(y - 0.3) < 0.05), outfit.print_color)
    front = shirt & (normal[..., 2] > 0.5)
    put(front & (x > 0.05) & (x < 0.11) & (y > 0.32) & (y < 0.38), outfit.print_color)  # a chest pocket
    if outfit.front_detail:
        put(front & ((x + 0.09) ** 2 + (y - 0.36) ** 2 < 0.035**2), outfit.shirt_alt)  # a logo
        placket = shirt & (normal[..., 2] > 0.3) & (np.abs(x) < 0.012)
        put(placket, outfit.shirt_alt)
        put(placket & (np.abs(x) < 0.006) & (np.mod(y, 0.07) < 0.012), (0.1, 0.1, 0.1))  # its buttons
    if outfit.jacket is not None or outfit.tie is not None:
        top_y, hem_y = y[shirt].max(), y[shirt].min()
        t = np.clip((y - hem_y) / max(top_y - hem_y, 1e-6), 0.0, 1.0)  # 0 at the hem, 1 at the shoulders
        facing = shirt & (normal[..., 2] > 0.25)
        if outfit.jacket_open:  # the top shows between the jacket's fronts down to the hem; a tie down to the belt
            opening = facing & (np.abs(x) < 0.055 + 0.035 * t)
            tie = facing & (np.abs(x) < 0.02 + 0.012 * (1 - t)) & (t > 0.08)
        else:  # a buttoned jacket: a V below the collar, the tie inside it
            opening = facing & (np.abs(x) < 0.1 * np.clip((t - 0.62) / 0.38, 0.0, 1.0))
            tie = opening & (np.abs(x) < 0.02 + 0.012 * (1 - t))
        if outfit.jacket is not None:
            put(shirt & ~opening, outfit.jacket)
        if outfit.tie is not None:
            put(tie, outfit.tie)
            put(tie & _stripes(y + x, 0.03), np.array(outfit.tie) * 0.55)
    put(region == REGIONS.index("collar"), outfit.shirt_alt)
    trousers = region == REGIONS.index("trousers")
    put(trousers, outfit.trousers)
    if outfit.trouser_pattern == "denim":
        tex[trousers] *= (1.0 + 0.25 * noise[trousers])[:, None]
    elif outfit.trouser_pattern == "side_stripe":
        side = trousers & (np.abs(normal[..., 0]) > 0.85)
        put(side, outfit.shirt_alt)
    skirt = region == REGIONS.index("skirt")
    put(skirt, outfit.trousers)
    put(skirt & _stripes(np.arctan2(x, z), 0.2), np.array(outfit.trousers) * 0.7)  # pleats
    shoes = region == REGIONS.index("shoes")
    put(shoes, outfit.shoes)
    put(shoes & (y < pos[..., 1][shoes].min() + 0.015 if shoes.any() else shoes), (0.92, 0.92, 0.9))
    hair = region == REGIONS.index("hair")
    put(hair, outfit.hair)
    tex[hair] *= (1.0 + 0.35 * noise[hair])[:, None]
    return np.clip(tex, 0.0, 1.0)


@dataclass
class SyntheticPerson:
    """A clothed, textured person ready to pose and render."""

    outfit: Outfit
    body: AnnyBody
    offsets: np.ndarray  # (V, 3) rest-pose clothing displacement
    render_to_body: np.ndarray  # (N,) body vertex of each render vertex
    renderer: MeshRenderer
    texture: np.ndarray  # (T, T, 3)
    regions: np.ndarray  # (V,) garment region per body vertex
    texel_regions: np.ndarray  # (T, T) garment region per texel
    texel_normals: np.ndarray  # (T, T, 3) rest-pose normal per texel
    object_rest: np.ndarray | None = None  # (N, 3) a held object's vertices, rigid with ``object_bone``, rest pose
    object_bone: int = -1

    def clothed_vertices(self, pose: np.ndarray, orient: np.ndarray, transl: np.ndarray) -> np.ndarray:
        """Posed clothed vertices in render-vertex order (clothing rides the body's skinning), then the held
        object's."""
        rest = self.body.rest_vertices + self.offsets
        verts = skin_to_pose(self.body, rest, self.body.skin_idx, self.body.skin_w, pose, orient, transl)[
            self.render_to_body
        ]
        if self.object_rest is None:
            return verts
        bone = bone_motion(self.body, pose, orient, transl)[self.object_bone].numpy()
        return np.concatenate([verts, self.object_rest @ bone[:3, :3].T + bone[:3, 3]])


def bone_motion(body: BodyModel, pose: np.ndarray, orient: np.ndarray, transl: np.ndarray):
    """(J, 4, 4) torch transforms from the body's rest pose to ``pose``: ``G_posed @ inverse(G_rest)``."""
    import torch

    from ..core.geometry import rigid_inverse

    rest = body.pose(body.zero_pose())
    posed = body.pose(pose, orient, transl)
    return torch.as_tensor(posed.bone_transforms) @ rigid_inverse(torch.as_tensor(rest.bone_transforms))


def skin_to_pose(
    body: BodyModel,
    rest: np.ndarray,
    skin_idx: np.ndarray,
    skin_w: np.ndarray,
    pose: np.ndarray,
    orient: np.ndarray,
    transl: np.ndarray,
) -> np.ndarray:
    """Rest-pose vertices (V, 3) with their (V, K) skinning, moved to ``pose`` by linear blend skinning."""
    import torch

    from ..model.skinning import forward_lbs

    mats = bone_motion(body, pose, orient, transl)
    return forward_lbs(torch.as_tensor(rest), torch.as_tensor(skin_idx), torch.as_tensor(skin_w), mats).numpy()


def make_person(seed: int, texture_size: int = 1024, outfit: Outfit | None = None) -> SyntheticPerson:
    """The person the seed draws (or ``outfit``, with its own seed), textured and ready to pose."""
    outfit = draw_outfit(seed) if outfit is None else outfit
    body = AnnyBody(outfit.phenotype)
    region = garment_regions(body, outfit)
    normals = vertex_normals(body.rest_vertices, body.faces)
    offsets = garment_offsets(body, outfit, region, normals)
    uniq, faces = seam_split(body.faces, body.face_uvs)
    body_idx, uv_idx = uniq[:, 0], uniq[:, 1]
    uvs = body.uvs[uv_idx]
    onehot = np.eye(len(REGIONS))[region[body_idx]]
    attrs = np.concatenate([body.rest_vertices[body_idx], normals[body_idx], onehot], 1)
    img, covered = rasterize_uv(uvs, faces, attrs, texture_size)
    tex_region = img[..., 6:].argmax(-1)
    tex_normal = img[..., 3:6] / np.maximum(np.linalg.norm(img[..., 3:6], axis=-1, keepdims=True), 1e-6)
    texture = paint_texture(outfit, tex_region, img[..., :3], tex_normal, np.random.default_rng(outfit.seed + 1))
    held = None
    if outfit.held_object is not None:
        held = held_folder(body, offsets, outfit)
        # The folder's colour goes into texels no body face reads; all its vertices sample them.
        free = np.argwhere(ndimage.binary_erosion(~covered, iterations=4))
        if not len(free):
            raise ValueError("no free texels left for the held object's colour")
        row, col = free[0]
        texture[row - 2 : row + 3, col - 2 : col + 3] = outfit.held_object
        uv = np.array([(col + 0.5) / texture_size, (row + 0.5) / texture_size])
        faces = np.concatenate([faces, held[1] + len(uvs)])
        uvs = np.concatenate([uvs, np.repeat(uv[None], len(held[0]), 0)])
    renderer = MeshRenderer(faces, MeshAppearance(uvs=uvs, texture=texture))
    person = SyntheticPerson(outfit, body, offsets, body_idx, renderer, texture, region, tex_region, tex_normal)
    if held is not None:
        person.object_rest, person.object_bone = held[0], held[2]
    return person


FOLDER_SIZE = (0.30, 0.24, 0.015)  # width, height, thickness of a held folder, metres


def held_folder(body: AnnyBody, offsets: np.ndarray, outfit: Outfit) -> tuple[np.ndarray, np.ndarray, int]:
    """A folder held upright in front of the chest in the outfit's posture, rigid with the upper spine: its
    (24, 3) vertices in the rest pose (four per side, so each side is flat), (12, 3) faces and the bone."""
    pose = posture(body, outfit.posture)
    bone = body.joint_index(body.semantic["spine_upper"])
    motion = bone_motion(body, pose, np.zeros(3), np.zeros(3)).numpy()
    rest = body.rest_vertices + offsets
    clothed = skin_to_pose(body, rest, body.skin_idx, body.skin_w, pose, np.zeros(3), np.zeros(3))
    posed = body.pose(pose).bone_transforms
    low, high = (posed[body.joint_index(body.semantic[n]), :3, 3] for n in ("spine_lower", "spine_upper"))
    centre = (low + high) / 2
    torso = body.vertex_parts() == PART_NAMES.index("torso")
    near = torso & (np.abs(clothed[:, 1] - centre[1]) < 0.12) & (np.abs(clothed[:, 0] - centre[0]) < 0.15)
    w, h, d = FOLDER_SIZE
    centre = np.array([centre[0], centre[1], clothed[near, 2].max() + 0.012 + d / 2])
    corners = np.array([[x, y, z] for x in (-w / 2, w / 2) for y in (-h / 2, h / 2) for z in (-d / 2, d / 2)])
    sides = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 2, 6, 4), (1, 5, 7, 3), (0, 4, 5, 1), (2, 3, 7, 6)]
    verts = np.concatenate([corners[list(q)] for q in sides]) + centre
    faces = np.concatenate([[[4 * k, 4 * k + 1, 4 * k + 2], [4 * k, 4 * k + 2, 4 * k + 3]] for k in range(6)])
    inverse = np.linalg.inv(motion[bone])
    return verts @ inverse[:3, :3].T + inverse[:3, 3], faces, bone


def synthesize(
    seed: int,
    out: str | Path,
    motion_name: str = "walk_in_place",
    size: int = 512,
    spp: int = 32,
    n_cameras: int = 23,
    texture_size: int = 1024,
    force: bool = False,
    person: str | None = None,
    photos: bool = False,
) -> Path:
    """Write a synthetic ``elicit-subject/1`` folder and its contact sheet, as a whole (a non-empty ``out``
    only with ``force``); returns the folder. ``person`` names one of ``PEOPLE`` instead of a seed; ``photos``
    also renders the second photos of a multi-photo test (:func:`extra_photos`)."""
    outfit = None if person is None else person_outfit(person)
    seed = seed if outfit is None else outfit.seed
    with folder_in_place(out, force) as tmp:
        _synthesize(seed, tmp, motion_name, size, spp, n_cameras, texture_size, outfit, person, photos)
    return Path(out)


def extra_photos(n_cameras: int, n_frames: int) -> dict[str, tuple[str, int]]:
    """A multi-photo test's second photos: ``back``, the ring camera nearest 180 degrees from the input, and
    ``side``, nearest 90 degrees, both in the motion's middle frame (another pose than the input's)."""
    frame = n_frames // 2
    return {"back": (f"cam{(n_cameras + 1) // 2:02d}", frame), "side": (f"cam{round(n_cameras / 4):02d}", frame)}


def _synthesize(
    seed: int,
    out: Path,
    motion_name: str,
    size: int,
    spp: int,
    n_cameras: int,
    texture_size: int,
    outfit: Outfit | None = None,
    person_name: str | None = None,
    photos: bool = False,
) -> None:
    start = time.perf_counter()
    person = make_person(seed, texture_size, outfit)
    body = person.body
    first = posture(body, person.outfit.posture)
    motion = motion_after_input(body, (first, np.zeros(3), _ground_shift(body, first)), motion_name)
    spec = {"model": "anny", "phenotype": outfit_phenotype(person.outfit)}
    extra = {"seed": seed, "motion": motion_name, "outfit": asdict(person.outfit)}
    if person_name is not None:
        extra["person"] = person_name
    label = f"synth {person_name}" if person_name else f"synth seed {seed}"
    if photos:
        extra["photos"] = extra_photos(n_cameras, len(motion))
    render_subject(out, person, spec, motion, size, spp, n_cameras, label, extra, start)


def motion_after_input(body: BodyModel, input_pose: tuple, motion_name: str) -> Motion:
    """The input pose (pose, global orientation, translation), then the frames of a built-in motion."""
    target = builtin_motion(motion_name, body)
    pose, orient, transl = input_pose
    return Motion(
        np.concatenate([np.asarray(pose)[None], target.pose]),
        np.concatenate([np.asarray(orient)[None], target.global_orient]),
        np.concatenate([np.asarray(transl)[None], target.transl]),
        None,
        30.0,
        f"{motion_name}+input",
    )


def render_subject(
    out: Path,
    person,
    spec: dict,
    motion: Motion,
    size: int,
    spp: int,
    n_cameras: int,
    label: str,
    extra: dict,
    start: float,
) -> None:
    """Render ``person`` (anything with ``clothed_vertices(pose, orient, transl)``, a ``renderer`` and a
    ``texture``) from a ring of ``n_cameras`` at the motion's first (input) frame, from the input camera at
    every other frame and at the (camera, frame) views ``extra["photos"]`` names, and write the subject, its
    texture and its contact sheet into ``out``."""
    from tqdm import tqdm

    focal = 650.0 * size / 512.0
    cameras = {c.name: c for c in ring_cameras(n=n_cameras, focal=focal, width=size, height=size)}
    input_cam = "cam00"
    jobs = [(name, 0) for name in cameras] + [(input_cam, f) for f in range(1, len(motion))]
    jobs += [tuple(view) for view in extra.get("photos", {}).values() if tuple(view) not in jobs]
    views = {}
    by_frame: dict[int, list[str]] = {}
    for cam, f in jobs:
        by_frame.setdefault(f, []).append(cam)
    for f, cams in tqdm(sorted(by_frame.items()), desc=label, unit="frame", leave=False):
        verts = person.clothed_vertices(*motion.frame(f))
        out_imgs = person.renderer.render(verts, [cameras[c] for c in cams], ("shaded",), spp=spp)
        for k, cam in enumerate(cams):
            alpha = out_imgs["alpha"][k]
            rgb = np.clip(out_imgs["shaded"][k], 0, 1) * (alpha[..., None] > 0.5)
            views[(cam, f)] = (rgb, alpha > 0.5)
    seconds = round(time.perf_counter() - start, 1)
    extra = {"synthetic": {**extra, "generator": "elicit_diffrender.inputs.synth", "seconds": seconds}}
    write_subject(out, spec, cameras, motion, input_cam, 0, views, extra)
    write_image(out / "texture.png", person.texture)
    write_contact_sheet(out, views, cameras, input_cam, len(motion))
    write_json(out / "synth.json", {**extra["synthetic"], "views": len(views)})


def outfit_phenotype(outfit: Outfit) -> dict:
    return {k: round(v, 4) for k, v in outfit.phenotype.items()}


def _ground_shift(body: AnnyBody, pose: np.ndarray) -> np.ndarray:
    floor = body.rest_vertices[:, 1].min()
    return np.array([0.0, floor - body.pose(pose).vertices[:, 1].min(), 0.0])


def write_contact_sheet(out: Path, views: dict, cameras: dict, input_cam: str, n_frames: int) -> Path:
    """Input | 5 ring views at the input frame, then 6 frames of the motion from the input camera."""
    names = list(cameras)
    ring = [names[k * len(names) // 6] for k in range(6)]
    frames = np.linspace(1, n_frames - 1, 6).astype(int)
    row1 = [views[(c, 0)][0] for c in ring]
    row2 = [views[(input_cam, int(f))][0] for f in frames]
    sheet = np.concatenate([np.concatenate(row1, 1), np.concatenate(row2, 1)], 0)
    step = max(1, sheet.shape[1] // 1536)
    return write_image(out / "contact_sheet.png", sheet[::step, ::step])
