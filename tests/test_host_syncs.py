"""A training step waits for the device at most once (the ray sampler's sample count); read-outs come every
``log_every`` steps. Also the set-up's coarse-to-fine signed distance against the plain one."""

import numpy as np
import pytest
import torch
from devices import DEVICE
from test_fit import TINY as FIT_TINY  # noqa: I001 - the tiny fit settings are shared with the fit tests

from elicit_diffrender.core.host_reads import count_host_reads, on_host
from elicit_diffrender.fit.config import make_config
from elicit_diffrender.fit.trainer import Trainer
from elicit_diffrender.model.field import EXACT_VOXELS, CanonicalField, grid_points, signed_distance

LOG_EVERY = 10
# test_fit's tiny fit, with 20 + 50 steps, a read-out every LOG_EVERY, and no previews or checkpoints in between
TINY = FIT_TINY + [
    "init_steps=20",
    "steps=50",
    f"log_every={LOG_EVERY}",
    "guard_every=20",
    "preview_every=100000",
    "checkpoint_every=100000",
]


def reads_per_step(trainer: Trainer) -> list[tuple[int, int, dict]]:
    """(stage, step, reads) of every step: the reads between one optimiser step's end and the next's."""
    per_step = []
    with count_host_reads() as reads:
        make = trainer.make_optimizer

        def counted_optimizer() -> None:
            make()
            step = trainer.opt.step

            def counted(*args, **kwargs):
                out = step(*args, **kwargs)
                per_step.append((trainer.stage, trainer.step + 1, reads.take()))
                return out

            trainer.opt.step = counted

        trainer.make_optimizer = counted_optimizer
        counted_optimizer()
        trainer.run()
    return per_step


@pytest.mark.parametrize(
    "sets",
    [[], ["learn_motion_weights=true", "refine_input_pose=true"]],
    ids=["baked warp", "learned warp and input pose (paper)"],
)
def test_a_step_reads_the_device_once_outside_the_read_outs(tmp_path, tiny_subject, sets):
    trainer = Trainer(tiny_subject, make_config("cpu-fast", None, TINY + sets), tmp_path / "run")
    per_step = reads_per_step(trainer)
    assert len(per_step) == 70
    # A step right after a read-out (the loss log every LOG_EVERY steps, and the guard and the spaces' rebuild,
    # which fall on multiples of it here) or a stage's first step may read more.
    quiet = [(stage, step, reads) for stage, step, reads in per_step if (step - 1) % LOG_EVERY]
    assert len(quiet) == 63
    for stage, step, reads in quiet:
        assert sum(reads.values()) <= 1, (stage, step, dict(reads))
    assert all(site[0] == "item" and site[1].startswith("model/volume.py") for _, _, r in quiet for site in r)
    # and the read-outs do read
    assert sum(sum(r.values()) for s, step, r in per_step if (step - 1) % LOG_EVERY == 0) > 8


def test_the_counter_sees_reads_and_branches_but_not_host_work():
    x = torch.ones(3, device=DEVICE)
    with count_host_reads() as reads:
        float(x.sum())
        if (x > 0).all():
            x[x > 0] += 1
        x.tolist()
        with on_host():
            int(torch.randint(0, 3, (1,)))  # a CPU generator's draw: host work
    kinds = sorted(kind for kind, _ in reads.sites)
    assert kinds == ["bool", "bool index", "float", "tolist"]
    assert all(site.startswith("outside") for _, site in reads.sites)


def test_a_nonfinite_loss_skips_its_update_and_is_counted(tmp_path, tiny_subject):
    trainer = Trainer(tiny_subject, make_config("cpu-fast", None, TINY + ["init_steps=0", "steps=10"]), tmp_path / "r")
    field, start, snapshot = trainer.avatar.field, trainer.start_stage_2, {}

    def started() -> None:
        start()
        snapshot.update(color=field.color.detach().clone(), density=field.density.detach().clone())

    trainer.start_stage_2 = started
    total = trainer.objective.total
    trainer.objective.total = lambda terms: total(terms) * float("nan")
    trainer.run()
    assert torch.equal(field.color.detach(), snapshot["color"])  # no update went through
    assert torch.equal(field.density.detach(), snapshot["density"])
    assert trainer.step == 10 and torch.isfinite(trainer.avatar.field.density).all()


def test_coarse_to_fine_distance_is_the_plain_one_where_it_is_read(tiny_subject):
    body = tiny_subject.body
    canon = body.pose(body.canonical_pose())
    from elicit_diffrender.body.template import vertex_normals

    normals = vertex_normals(canon.vertices, body.faces)
    lo, hi = canon.vertices.min(0) - 0.1, canon.vertices.max(0) + 0.1
    field = CanonicalField(torch.tensor(np.stack([lo, hi]), dtype=torch.float32), 0.012)
    fast = field.body_distance(canon.vertices, normals)
    pts = grid_points(field.box.double(), field.shape).reshape(-1, 3).numpy()
    plain = signed_distance(pts, canon.vertices, normals).reshape(field.shape)
    exact = np.abs(fast) < EXACT_VOXELS * field.voxel_size
    assert exact.mean() < 0.5  # most of the box was bounded, not computed
    np.testing.assert_array_equal(fast[exact], plain[exact])
    np.testing.assert_array_equal(fast < 0, plain < 0)  # the inside is always computed
    assert (np.abs(plain[~exact]) >= EXACT_VOXELS * field.voxel_size).all()
    assert (fast[~exact] <= plain[~exact]).all()  # a bound from below
