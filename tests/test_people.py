"""Named synthetic people: postures aimed limb by limb, clothes with front-only details, a held folder."""

import numpy as np
import pytest

from elicit_diffrender.inputs.people import PEOPLE
from elicit_diffrender.inputs.postures import POSTURES, SEGMENTS, posture, standing
from elicit_diffrender.inputs.synth import REGIONS, make_person, person_outfit, synthesize


def _joints(body, pose) -> dict:
    frames = body.pose(pose).bone_transforms
    return {n: frames[body.joint_index(body.semantic[n]), :3, 3] for n in body.semantic}


@pytest.mark.parametrize("name", sorted(POSTURES))
def test_every_posture_points_its_limbs_where_it_says(anny_body, name):
    joint = _joints(anny_body, posture(anny_body, name))
    for segment, target in POSTURES[name].items():
        head, tail = SEGMENTS[segment]
        d = joint[tail] - joint[head]
        cos = d @ np.asarray(target) / np.linalg.norm(d) / np.linalg.norm(target)
        assert cos > np.cos(np.radians(0.5)), (name, segment)


def test_a_posture_leaves_the_limbs_it_does_not_name_standing(anny_body):
    still = _joints(anny_body, standing(anny_body))
    seated = _joints(anny_body, posture(anny_body, "seated"))
    raised = _joints(anny_body, posture(anny_body, "arms_raised"))
    for name in ("l_elbow", "l_wrist", "r_wrist"):
        np.testing.assert_allclose(seated[name], still[name], atol=1e-9)  # the legs changed, not the arms
    for name in ("l_knee", "r_ankle"):
        np.testing.assert_allclose(raised[name], still[name], atol=1e-9)
    assert abs(seated["l_knee"][1] - seated["l_hip"][1]) < 0.08 and seated["l_knee"][2] - seated["l_hip"][2] > 0.3
    assert seated["l_hip"][1] - seated["l_ankle"][1] > 0.3  # seated: thighs level and forward, shins down


def test_every_named_person_is_a_seed_and_changes():
    for name, (seed, changes) in PEOPLE.items():
        outfit = person_outfit(name)
        assert outfit.seed == seed and outfit.posture in POSTURES
        assert all(getattr(outfit, key) == value for key, value in changes.items())
    with pytest.raises(ValueError, match="unknown person"):
        person_outfit("nobody")


def _share(texels: np.ndarray, colour) -> float:
    """Share of the texels within 0.02 of a colour."""
    return float((np.abs(texels - np.asarray(colour)).max(-1) < 0.02).mean()) if len(texels) else 0.0


def test_an_open_jacket_shows_the_shirt_and_tie_in_front_only():
    person = make_person(0, texture_size=256, outfit=person_outfit("open_jacket_tie"))
    tex, region, normal = person.texture, person.texel_regions, person.texel_normals
    shirt = region == REGIONS.index("shirt")
    front, back = tex[shirt & (normal[..., 2] > 0.6)], tex[shirt & (normal[..., 2] < -0.6)]
    outfit = person.outfit
    assert _share(back, outfit.jacket) > 0.98  # the back is the jacket, all of it
    assert _share(front, outfit.shirt) > 0.05 and _share(front, outfit.jacket) > 0.3  # the shirt between its fronts
    tie = _share(front, outfit.tie) + _share(front, 0.55 * np.asarray(outfit.tie))  # the tie and its stripes
    assert tie > 0.01 and _share(back, outfit.tie) == 0.0


def test_a_held_folder_shows_in_the_front_view_not_from_behind(tmp_path):
    from elicit_diffrender.data.subject import load_subject

    out = synthesize(0, tmp_path / "s", "rest", size=128, spp=2, n_cameras=4, texture_size=256, person="held_folder")
    subject = load_subject(out)
    hue = np.asarray(person_outfit("held_folder").held_object)
    hue = hue / hue.sum()

    def folder_pixels(image: np.ndarray) -> int:
        luma = image.sum(-1)
        return int(((np.abs(image / np.maximum(luma, 1e-6)[..., None] - hue).max(-1) < 0.02) & (luma > 0.4)).sum())

    front, back = folder_pixels(subject.image("cam00", 0)), folder_pixels(subject.image("cam02", 0))
    assert front > 30 and back < 0.2 * front


def test_synth_takes_one_of_seed_person_and_mesh(capsys):
    from elicit_diffrender.apps.cli import main

    for extra in (["--seed", "1", "--person", "seated"], ["--person", "seated", "--mesh", "a.obj"]):
        with pytest.raises(SystemExit) as done:
            main(["synth", "--out", "o", *extra])
        err = capsys.readouterr().err.strip()
        assert done.value.code == 2 and len(err.splitlines()) == 1 and "not allowed with argument" in err, err
