"""``elicit batch`` on Ray (an embedded local Ray, and a cluster joined by address) and the fit's thread pools."""

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_fit import TINY as FIT_TINY  # noqa: I001 - the tiny fit settings are shared with the fit tests

from elicit_diffrender.apps import batch
from elicit_diffrender.apps.batch import BatchError, find_jobs, parse_steps
from elicit_diffrender.apps.cli import main
from elicit_diffrender.inputs.synth import synthesize

TINY = [x for kv in [*FIT_TINY, "init_steps=10", "steps=10"] for x in ("--set", kv)]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """Two good subjects and one photo that is not an image."""
    root = tmp_path_factory.mktemp("batch_in")
    for seed in (5, 7):
        synthesize(seed, root / f"subject{seed}", size=64, spp=2, n_cameras=3, texture_size=128)
    (root / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\nnot an image")
    return root


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


@pytest.mark.slow
def test_batch_on_local_ray(inputs, tmp_path, capsys, monkeypatch):
    out = tmp_path / "batch"
    args = ["batch", str(inputs), "--out", str(out), "--size", "32", *TINY]
    assert main(args) == 2  # one job failed
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()[-1]
    assert "1 of 3 jobs failed; job broken" in err and "broken.png: unreadable photo" in err
    assert "Traceback" not in captured.err and "job broken failed" in captured.out
    jobs = {r["name"]: r for r in _summary(out)["jobs"]}
    assert set(jobs) == {"broken", "subject5", "subject7"}
    assert jobs["broken"]["status"] == "failed" and "unreadable photo" in jobs["broken"]["error"]
    for name in ("subject5", "subject7"):
        assert jobs[name]["status"] == "done" and jobs[name]["error"] is None and jobs[name]["fit_seconds"] > 0
        for link in ("video", "contact_sheet", "avatar"):
            assert (out / jobs[name][link]).is_file()
        assert (out / name / "run" / "avatar.safetensors").is_file()
        log = (out / name / "run" / "log.txt").read_text()
        assert "thread pools sized to 1 CPUs" in log  # each task's share of the cores
    md = (out / "summary.md").read_text()
    assert "2 done, 1 failed of 3" in md and "unreadable photo" in md

    # A rerun does no work: nothing is rewritten and Ray is not even started.
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and p.parent != out}

    def no_ray(*args):
        raise AssertionError("a rerun of a finished batch started Ray")

    monkeypatch.setattr(batch, "start_ray", no_ray)
    assert main(args) == 2
    monkeypatch.undo()
    assert stamps == {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and p.parent != out}
    assert _summary(out)["counts"] == {"done": 2, "failed": 1, "pending": 0, "running": 0}

    # A job killed during its fit (its checkpoint written, no avatar yet) resumes from the checkpoint.
    run = out / "subject7" / "run"
    (run / "avatar.safetensors").unlink()
    (run / "run.json").unlink()
    (out / "subject7" / "job.json").write_text(json.dumps({"status": "running"}))
    assert main([args[0], str(inputs / "subject7"), *args[2:]]) == 0
    assert (run / "avatar.safetensors").is_file() and "resumed from" in (run / "log.txt").read_text()
    assert (out / "subject5" / "job.json").stat().st_mtime_ns == stamps[out / "subject5" / "job.json"]


@pytest.mark.slow
def test_batch_joins_a_cluster_by_address(inputs, tmp_path):
    """A Ray head started apart (as on a cluster): the batch ships this package in the runtime environment."""
    ray = Path(sys.executable).with_name("ray")
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED="0")
    head = subprocess.Popen(
        [str(ray), "start", "--head", "--block", "--num-cpus=2", "--include-dashboard=false", "--port=6391"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        time.sleep(8)
        out = tmp_path / "batch"
        cmd = [
            sys.executable, "-m", "elicit_diffrender.apps.cli", "batch", str(inputs / "subject5"), "--out", str(out),
            "--steps", "fit", "--address", "auto", *TINY,
        ]  # fmt: skip
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr[-2000:]
        (job,) = _summary(out)["jobs"]
        assert job["status"] == "done" and (out / "subject5" / "run" / "avatar.safetensors").is_file()
        shipped = list(Path("/tmp/ray/session_latest/runtime_resources/py_modules_files").glob("*/elicit_diffrender"))
        assert shipped and all((p / "kernels" / "skinning.py").is_file() for p in shipped)
    finally:
        head.terminate()
        head.wait(timeout=60)


def test_job_discovery(inputs, tmp_path):
    jobs = find_jobs([inputs])
    assert [j.name for j in jobs] == ["broken", "subject5", "subject7"]
    assert [j.is_photo for j in jobs] == [True, False, False]
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "me.jpg").write_bytes(b"x")
    (tmp_path / "a" / "me_mask.png").write_bytes(b"x")
    (job,) = find_jobs([tmp_path / "a"])
    assert job.masks == (tmp_path / "a" / "me_mask.png",)  # a mask beside its photo is the photo's, not a job
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "me.png").write_bytes(b"x")
    with pytest.raises(BatchError, match="would share the job folder 'me'"):
        find_jobs([tmp_path / "a", tmp_path / "b"])
    with pytest.raises(BatchError, match="no such file"):
        find_jobs([tmp_path / "missing.png"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(BatchError, match="no photos"):
        find_jobs([tmp_path / "empty"])
    # --per-folder: a folder of photos is one person, one multi-photo job in name order, each with its mask.
    (tmp_path / "person").mkdir()
    for name in ("2_back.png", "1_front.jpg", "1_front_mask.png"):
        (tmp_path / "person" / name).write_bytes(b"x")
    (job,) = find_jobs([tmp_path / "person"], per_folder=True)
    folder = tmp_path / "person"
    assert job.name == "person" and job.is_photo
    assert job.photos == (folder / "1_front.jpg", folder / "2_back.png")
    assert job.masks == (folder / "1_front_mask.png", None)
    stamp = job.stamp()
    (folder / "2_back.png").write_bytes(b"xy")  # replacing any photo retries a failed job
    assert job.stamp() != stamp
    assert [j.name for j in find_jobs([tmp_path / "person"])] == ["1_front", "2_back"]  # without it: a job each
    assert parse_steps("export, fit") == ("fit", "export")
    with pytest.raises(BatchError, match="--steps"):
        parse_steps("fit,paint")


def test_bad_batch_options_give_one_line(tmp_path, capsys):
    assert main(["batch", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 2
    assert "nothing: no such file or folder" in capsys.readouterr().err
    assert main(["batch", str(tmp_path), "--out", str(tmp_path / "o"), "--steps", "paint"]) == 2
    assert "--steps" in capsys.readouterr().err
    assert main(["batch", str(tmp_path), "--out", str(tmp_path / "o"), "--set", "bogus=1"]) == 2
    assert "unknown config key 'bogus'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "prefix, env, expect",
    [
        (["taskset", "-c", "0"], {}, 1),  # the affinity mask
        ([], {"OMP_NUM_THREADS": "1"}, 1),  # Ray's num_cpus
        ([], {}, min(len(os.sched_getaffinity(0)), os.cpu_count() or 1)),
    ],
)
def test_thread_pools_follow_the_cpus_given(prefix, env, expect):
    if prefix and shutil.which(prefix[0]) is None:
        pytest.skip("taskset is not installed")
    code = (
        "import torch; from elicit_diffrender.core.device import size_thread_pools, cpu_threads; import drjit as dr; "
        "n = size_thread_pools(); print(n, torch.get_num_threads(), dr.thread_count(), cpu_threads())"
    )
    base = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    done = subprocess.run([*prefix, sys.executable, "-c", code], env=base | env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-1000:]
    assert done.stdout.split()[-4:] == [str(expect)] * 3 + [str(min(expect, 8))]


def _descendants(pid: int) -> set[int]:
    """Every living process below ``pid`` (read from /proc)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.add(child)
            todo.append(child)
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.slow
def test_sigterm_stops_the_batch_and_its_ray_agents(inputs, tmp_path):
    """Ray's agents (raylet, GCS, workers) outlived a killed batch driver by over a minute."""
    cmd = [
        sys.executable, "-m", "elicit_diffrender.apps.cli", "batch", str(inputs / "subject5"), "--out",
        str(tmp_path / "batch"), "--steps", "fit", *[x for kv in FIT_TINY for x in ("--set", kv)],
        "--set", "init_steps=2000", "--set", "steps=2000",
    ]  # fmt: skip
    driver = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 180
    agents: set[int] = set()
    while time.monotonic() < deadline and not any("raylet" in _cmdline(p) for p in agents):
        time.sleep(1)
        agents |= _descendants(driver.pid)
    time.sleep(5)  # the fit task is running in a Ray worker
    agents |= _descendants(driver.pid)
    assert any("raylet" in _cmdline(p) for p in agents), "Ray did not start"
    driver.send_signal(15)
    err = driver.communicate(timeout=60)[1]
    assert driver.returncode == 128 + 15 and "Traceback" not in err, err[-2000:]
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and any(_alive(p) for p in agents):
        time.sleep(0.5)
    left = [f"{p}: {_cmdline(p)[:80]}" for p in agents if _alive(p)]
    assert not left, left


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""
