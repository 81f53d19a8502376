"""The Pareto fronts that ``scripts/bench_accuracy_time.py`` reports."""

import importlib.util
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "bench_accuracy_time.py"
spec = importlib.util.spec_from_file_location("bench_accuracy_time", SCRIPT)
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)


def point(name: str, fit_s: float, psnr: float, ssim: float) -> dict:
    return {"name": name, "fit_s": fit_s, "psnr": psnr, "ssim": ssim}


def test_psnr_front_drops_slower_and_worse_points():
    pts = [point("slow", 300, 24.5, 0.88), point("fast", 250, 24.8, 0.87), point("fastest", 100, 23.0, 0.85)]
    assert bench.pareto(pts) == ["fast", "fastest"]


def test_psnr_ssim_front_keeps_a_point_that_wins_on_ssim():
    pts = [point("slow", 300, 24.5, 0.88), point("fast", 250, 24.8, 0.87), point("fastest", 100, 23.0, 0.85)]
    assert bench.pareto(pts, ("psnr", "ssim")) == ["slow", "fast", "fastest"]


def test_a_point_better_on_everything_leaves_one_front():
    pts = [point("a", 300, 24.5, 0.88), point("b", 250, 26.0, 0.89)]
    assert bench.pareto(pts, ("psnr", "ssim")) == ["b"]


def test_ties_do_not_dominate():
    pts = [point("a", 300, 24.5, 0.88), point("b", 300, 24.5, 0.88)]
    assert bench.pareto(pts) == ["a", "b"]
