"""The synthetic clothed-subject generator: valid, deterministic, clothed, with a distinct back."""

import numpy as np
import pytest

from elicit_diffrender.data.mesh_render import MeshRenderer
from elicit_diffrender.data.subject import load_subject
from elicit_diffrender.inputs.synth import REGIONS, draw_outfit, garment_regions, make_person, synthesize


@pytest.fixture(scope="module")
def small_subject(tmp_path_factory):
    return synthesize(3, tmp_path_factory.mktemp("synth") / "s3", size=96, spp=4, n_cameras=4, texture_size=256)


def test_subject_is_valid_with_contact_sheet(small_subject):
    s = load_subject(small_subject)
    assert s.body_spec["model"] == "anny" and s.input_camera == "cam00" and s.input_frame == 0
    views = s.views()
    assert {("cam00", 0), ("cam02", 0), ("cam00", len(s.motion) - 1)} <= set(views)
    assert len(views) == 4 + len(s.motion) - 1
    assert (small_subject / "contact_sheet.png").is_file()
    assert s.mask("cam00", 0).sum() > 300


def test_deterministic_per_seed(small_subject, tmp_path):
    again = synthesize(3, tmp_path / "again", size=96, spp=4, n_cameras=4, texture_size=256)
    a, b = load_subject(small_subject), load_subject(again)
    np.testing.assert_array_equal(a.image("cam01", 0), b.image("cam01", 0))
    assert draw_outfit(3) == draw_outfit(3) and draw_outfit(3) != draw_outfit(4)


def test_clothing_is_thicker_than_the_body_and_the_back_differs(small_subject):
    s = load_subject(small_subject)
    body = s.body
    cam = s.cameras["cam00"]
    naked = MeshRenderer(body.faces).render(body.pose(*s.motion.frame(0)).vertices, [cam], ("mask",))["mask"][0] > 0
    clothed = s.mask("cam00", 0)
    assert clothed.sum() > naked.sum() * 1.02
    assert (naked & ~clothed).sum() < 0.05 * naked.sum()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_back_carries_a_print_the_front_does_not(seed):
    person = make_person(seed, texture_size=256)
    shirt = person.texel_regions == REGIONS.index("shirt")
    is_print = np.all(np.abs(person.texture - np.array(person.outfit.print_color)) < 1e-6, axis=-1)
    back = shirt & (person.texel_normals[..., 2] < -0.5)
    front = shirt & (person.texel_normals[..., 2] > 0.5)
    assert is_print[back].mean() > 3 * is_print[front].mean() and is_print[back].mean() > 0.03


def test_garment_regions_cover_the_body(anny_body):
    outfit = draw_outfit(0)
    region = garment_regions(anny_body, outfit)
    counts = np.bincount(region, minlength=len(REGIONS))
    assert all(counts[REGIONS.index(r)] > 50 for r in ("skin", "shirt", "trousers", "shoes", "hair"))
    heights = anny_body.rest_vertices[:, 1]
    assert heights[region == REGIONS.index("shoes")].max() < heights[region == REGIONS.index("trousers")].max()
    assert heights[region == REGIONS.index("hair")].min() > heights[region == REGIONS.index("shirt")].mean()


def test_loose_garments_stand_off_the_body():
    """A skirt flares from the waist, a loose top stands off towards its hem, voluminous hair raises the head."""
    skirted = make_person(14, texture_size=256)  # a skirt and 13 cm of hair
    assert skirted.outfit.skirt and skirted.outfit.hair_volume > 0.1
    rest = skirted.body.rest_vertices
    clothed = rest + skirted.offsets
    skirt = skirted.regions == REGIONS.index("skirt")
    body = skirted.body
    pelvis = body.pose(body.zero_pose()).bone_transforms[body.joint_index(body.semantic["pelvis"]), :3, 3]
    hem = skirt & (rest[:, 1] < rest[skirt, 1].min() + 0.03)
    radius = np.linalg.norm((clothed[hem] - pelvis)[:, [0, 2]], axis=1)
    assert radius.min() > 0.12  # the hem is a ring round both legs, not two tubes
    hair = skirted.regions == REGIONS.index("hair")
    assert clothed[hair, 1].max() > rest[:, 1].max() + 0.08
    loose = make_person(1, texture_size=256)
    assert loose.outfit.loose_top
    shirt = loose.regions == REGIONS.index("shirt")
    assert np.linalg.norm(loose.offsets[shirt], axis=1).max() > 0.05
