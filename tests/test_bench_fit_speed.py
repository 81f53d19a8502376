"""When ``scripts/bench_fit_speed.py`` judges the time ratio: only for two fits that ran in one go."""

import importlib.util
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "bench_fit_speed.py"
spec = importlib.util.spec_from_file_location("bench_fit_speed", SCRIPT)
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)


def test_two_fits_of_this_run_ran_in_one_go_however_long_they_took():
    assert bench.ran_in_one_go([True, True], [0.0, 10 * 3600.0], 150.0)


def test_a_reused_fit_beside_a_new_one_did_not():
    assert not bench.ran_in_one_go([False, True], [0.0, 200.0], 150.0)
    assert not bench.ran_in_one_go([True, False], [0.0, 200.0], 150.0)


def test_two_reused_fits_ran_in_one_go_only_when_they_finished_close_together():
    close = bench.SAME_RUN_S + 150.0
    assert bench.ran_in_one_go([False, False], [1000.0, 1000.0 + close], 150.0)
    assert not bench.ran_in_one_go([False, False], [1000.0, 1001.0 + close], 150.0)
    assert not bench.ran_in_one_go([False, False], [5 * 3600.0, 0.0], 150.0)  # the morning's against the evening's
