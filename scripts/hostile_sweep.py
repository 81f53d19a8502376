#!/usr/bin/env python
"""Hostile and careless inputs across every command, beyond the cases ``tests/test_hostile.py`` pins down.

Builds a tiny subject and a tiny fit, then hands each command broken, forged or absurd inputs and records, per case:
the exit code, how many lines reached stderr, whether a traceback showed, the peak memory and whether any file
outside the case's output folder changed. A case passes with a clean refusal (exit 2, one stderr line, no
traceback) or a clean success (exit 0) where the input is odd but valid. Writes
``docs/benchmarks/hostile_sweep.{json,md}``.

    python scripts/hostile_sweep.py
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

from elicit_diffrender.apps.benchtools import ROOT_DIR, write_report

WRAPPER = (
    "import resource, subprocess, sys; "
    "done = subprocess.run([sys.executable, '-m', 'elicit_diffrender.apps.cli', *sys.argv[1:]]); "
    "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss // 1024); sys.exit(done.returncode)"
)
TINY = [
    "init_steps=20", "steps=20", "crop_size=32", "label_size=96", "voxel_size=0.03", "samples_per_ray=24",
    "ring_cameras=8", "occupancy_cell=0.06", "preview_every=1000", "checkpoint_every=10", "weight_grid=16",
]  # fmt: skip
SETS = [x for kv in TINY for x in ("--set", kv)]


def _snapshot(root: Path, skip: Path) -> dict[str, tuple[int, int]]:
    out = {}
    for path in root.rglob("*"):
        if path == skip or skip in path.parents or not path.is_file() or path.is_symlink():
            continue
        info = path.stat()
        out[str(path)] = (info.st_size, info.st_mtime_ns)
    return out


def _png(path: Path, array: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array).save(path)
    return path


def _copy_subject(base: Path, dest: Path) -> Path:
    subprocess.run(["cp", "-r", str(base), str(dest)], check=True)
    return dest


def _edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def build_cases(root: Path, subject: Path, run: Path) -> list[tuple[str, str, list[str], Path]]:
    """(command, what is handed in, arguments, output folder) per case; payloads are written under ``root``."""
    cases = []
    n = 0

    def case(cmd: str, what: str, args: list[str]) -> Path:
        nonlocal n
        n += 1
        out = root / f"out{n:02d}"
        cases.append((cmd, what, [a.replace("{OUT}", str(out)) for a in args], out))
        return out

    p = root / "payload"
    p.mkdir()
    photo = Image.open(sorted((subject / "images").rglob("*.png"))[0])
    size = photo.size
    _png(p / "photo.png", np.asarray(photo.convert("RGB")))
    # synth
    case("synth", "--size 0", ["synth", "--seed", "1", "--size", "0", "--out", "{OUT}"])
    case("synth", "--size 10^9", ["synth", "--seed", "1", "--size", "1000000000", "--out", "{OUT}"])
    case("synth", "--mesh that does not exist", ["synth", "--mesh", str(p / "none.obj"), "--out", "{OUT}"])
    (p / "garbage.obj").write_bytes(os.urandom(4096))
    case("synth", "--mesh of random bytes", ["synth", "--mesh", str(p / "garbage.obj"), "--out", "{OUT}"])
    (p / "badface.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99\n")
    case(
        "synth",
        "--mesh with a face index past the vertices",
        ["synth", "--mesh", str(p / "badface.obj"), "--out", "{OUT}"],
    )
    (p / "nan.obj").write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    case("synth", "--mesh with a NaN vertex", ["synth", "--mesh", str(p / "nan.obj"), "--out", "{OUT}"])
    (p / "escape.mtl").write_text("newmtl m\nmap_Kd ../../../../../../etc/passwd\n")
    (p / "escape.obj").write_text("mtllib escape.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nusemtl m\nf 1/1 2/1 3/1\n")
    case(
        "synth",
        "--mesh whose MTL names /etc/passwd as texture",
        ["synth", "--mesh", str(p / "escape.obj"), "--out", "{OUT}"],
    )
    case("synth", "--person unknown", ["synth", "--person", "nobody", "--out", "{OUT}"])
    # prepare
    (p / "text.png").write_text("not a picture")
    case("prepare", "a text file named .png", ["prepare", str(p / "text.png"), "--out", "{OUT}"])
    _png(p / "tiny.png", np.zeros((1, 1, 3), np.uint8))
    case("prepare", "a 1x1 photo", ["prepare", str(p / "tiny.png"), "--out", "{OUT}"])
    _png(p / "black.png", np.zeros((64, 48, 3), np.uint8))
    _png(p / "black_mask.png", np.zeros((64, 48), np.uint8))
    case(
        "prepare",
        "a black photo with an empty mask",
        ["prepare", str(p / "black.png"), "--mask", str(p / "black_mask.png"), "--out", "{OUT}"],
    )
    _png(p / "small_mask.png", np.full((10, 10), 255, np.uint8))
    case(
        "prepare",
        "a mask of another size",
        ["prepare", str(p / "photo.png"), "--mask", str(p / "small_mask.png"), "--out", "{OUT}"],
    )
    case("prepare", "--focal -5", ["prepare", str(p / "photo.png"), "--focal", "-5", "--out", "{OUT}"])
    case("prepare", "--focal nan", ["prepare", str(p / "photo.png"), "--focal", "nan", "--out", "{OUT}"])
    case("prepare", "a folder as the photo", ["prepare", str(p), "--out", "{OUT}"])
    (p / "cut.png").write_bytes((p / "photo.png").read_bytes()[:300])
    case("prepare", "a truncated PNG", ["prepare", str(p / "cut.png"), "--out", "{OUT}"])
    Image.new("CMYK", size, (0, 0, 0, 0)).save(p / "cmyk.jpg")
    _png(p / "cmyk_mask.png", np.zeros(size[::-1], np.uint8))
    case(
        "prepare",
        "a CMYK JPEG",
        ["prepare", str(p / "cmyk.jpg"), "--mask", str(p / "cmyk_mask.png"), "--out", "{OUT}"],
    )
    os.mkfifo(p / "fifo.png")
    case("prepare", "a named pipe as the photo", ["prepare", str(p / "fifo.png"), "--out", "{OUT}"])

    # fit: broken subjects
    def broken(name: str, edit) -> Path:
        dest = _copy_subject(subject, p / name)
        edit(dest)
        return dest

    s = broken("no_json", lambda d: (d / "subject.json").unlink())
    case("fit", "a subject without subject.json", ["fit", str(s), "--out", "{OUT}", *SETS])
    s = broken("list_json", lambda d: (d / "subject.json").write_text("[]"))
    case("fit", "subject.json holding a list", ["fit", str(s), "--out", "{OUT}", *SETS])
    s = broken("frames", lambda d: _edit_json(d / "subject.json", lambda j: j.update(frames=-1)))
    case("fit", "subject.json frames -1", ["fit", str(s), "--out", "{OUT}", *SETS])
    cams = "cameras.json"

    def k_strings(d: Path) -> None:
        def edit(j):
            for cam in j.values() if isinstance(j, dict) else j:
                if isinstance(cam, dict) and "K" in cam:
                    cam["K"] = [["a", "b", "c"]] * 3

        _edit_json(d / cams, edit)

    s = broken("k_strings", k_strings)
    case("fit", "camera K of strings", ["fit", str(s), "--out", "{OUT}", *SETS])

    def k_zero(d: Path) -> None:
        def edit(j):
            for cam in j.values() if isinstance(j, dict) else j:
                if isinstance(cam, dict) and "K" in cam:
                    cam["K"] = [[0, 0, 0]] * 3

        _edit_json(d / cams, edit)

    s = broken("k_zero", k_zero)
    case("fit", "camera K all zero", ["fit", str(s), "--out", "{OUT}", *SETS])
    s = broken("no_images", lambda d: subprocess.run(["rm", "-r", str(d / "images")], check=True))
    case("fit", "a subject without its images", ["fit", str(s), "--out", "{OUT}", *SETS])

    def empty_masks(d: Path) -> None:
        for m in (d / "masks").rglob("*.png"):
            _png(m, np.zeros(Image.open(m).size[::-1], np.uint8))

    s = broken("empty_masks", empty_masks)
    case("fit", "every mask empty", ["fit", str(s), "--out", "{OUT}", *SETS])
    case("fit", "--set steps=1e30", ["fit", str(subject), "--out", "{OUT}", *SETS, "--set", "steps=1e30"])
    case("fit", "--set lr=-1", ["fit", str(subject), "--out", "{OUT}", *SETS, "--set", "lr=-1"])
    case("fit", "--set with no '='", ["fit", str(subject), "--out", "{OUT}", "--set", "steps"])
    case(
        "fit",
        "--set clip_pretrained=/etc/hostname",
        [
            "fit",
            str(subject),
            "--out",
            "{OUT}",
            *SETS,
            "--set",
            "encoder=clip",
            "--set",
            "clip_pretrained=/etc/hostname",
        ],
    )
    (p / "a_file").write_text("x")
    case("fit", "--out is a file", ["fit", str(subject), "--out", str(p / "a_file"), *SETS])
    case("fit", "--preset unknown", ["fit", str(subject), "--out", "{OUT}", "--preset", "turbo"])

    # render / export / eval / view on broken runs
    def broken_run(name: str, edit) -> Path:
        dest = p / name
        subprocess.run(["cp", "-r", str(run), str(dest)], check=True)
        edit(dest)
        return dest

    empty = p / "empty_run"
    empty.mkdir()
    case("render", "an empty run folder", ["render", str(empty), "--out", "{OUT}"])
    r = broken_run(
        "cut_avatar", lambda d: (d / "avatar.safetensors").write_bytes((d / "avatar.safetensors").read_bytes()[:5000])
    )
    case("render", "a truncated avatar", ["render", str(r), "--out", "{OUT}", "--size", "32"])

    def huge_header(d: Path) -> None:
        header = json.dumps({"x": {"dtype": "F32", "shape": [1 << 40], "data_offsets": [0, 4 << 40]}}).encode()
        (d / "avatar.safetensors").write_bytes(len(header).to_bytes(8, "little") + header)

    r = broken_run("huge_avatar", huge_header)
    case("render", "an avatar header claiming 4 TB", ["render", str(r), "--out", "{OUT}", "--size", "32"])
    case("render", "--motion unknown", ["render", str(run), "--out", "{OUT}", "--motion", "moonwalk"])
    (p / "rig.xml").write_text("<scene><sensor type='perspective'><float name='fov' value='")
    case("render", "--cameras of broken XML", ["render", str(run), "--out", "{OUT}", "--cameras", str(p / "rig.xml")])
    case("render", "--size -1", ["render", str(run), "--out", "{OUT}", "--size", "-1"])
    case("render", "--fps 0", ["render", str(run), "--out", "{OUT}", "--fps", "0"])
    case("export", "--resolution 0", ["export", str(run), "--out", "{OUT}/a.glb", "--resolution", "0"])
    case("export", "--faces -1", ["export", str(run), "--out", "{OUT}/a.glb", "--faces", "-1"])
    case(
        "export",
        "--out below a file",
        ["export", str(run), "--out", str(p / "a_file" / "a.glb"), "--resolution", "0.05"],
    )
    case("eval", "a subject that does not exist", ["eval", str(run), str(p / "nowhere"), "--out", "{OUT}/m.json"])
    case("eval", "--max-views 0", ["eval", str(run), str(subject), "--out", "{OUT}/m.json", "--max-views", "0"])
    case("eval", "--scale nan", ["eval", str(run), str(subject), "--out", "{OUT}/m.json", "--scale", "nan"])
    (p / "junk.glb").write_bytes(b"glTF" + os.urandom(200))
    case("view", "a .glb of random bytes", ["view", str(p / "junk.glb"), "--out", "{OUT}/v.html"])
    (p / "long.glb").write_bytes(b"glTF" + (2).to_bytes(4, "little") + (1 << 31).to_bytes(4, "little")
                                 + (1 << 31).to_bytes(4, "little") + b"JSON" + b"{}")  # fmt: skip
    case("view", "a .glb whose chunk claims 2 GB", ["view", str(p / "long.glb"), "--out", "{OUT}/v.html"])
    # rig
    case("rig", "--n 0", ["rig", "ring", "--n", "0", "--out", "{OUT}/r.xml"])
    case("rig", "--n 10^9", ["rig", "ring", "--n", "1000000000", "--out", "{OUT}/r.xml"])
    case("rig", "--focal 0", ["rig", "ring", "--focal", "0", "--out", "{OUT}/r.xml"])
    case("rig", "--size 1000000", ["rig", "ring", "--size", "1000000", "--out", "{OUT}/r.xml"])
    # import
    (p / "zju_empty").mkdir()
    case("import", "an empty ZJU folder", ["import", "zju", str(p / "zju_empty"), "--out", "{OUT}"])
    (p / "wild_empty").mkdir()
    case("import", "an empty in-the-wild folder", ["import", "elicit-wild", str(p / "wild_empty"), "--out", "{OUT}"])
    np.savez(p / "objects.npz", v_template=np.array([object()], dtype=object))
    case(
        "import",
        "--smpl .npz holding Python objects",
        ["import", "zju", str(p / "zju_empty"), "--smpl", str(p / "objects.npz"), "--frames", "0", "--out", "{OUT}"],
    )
    case("import", "--frames -1", ["import", "zju", str(p / "zju_empty"), "--frames", "-1", "--out", "{OUT}"])
    # weights
    case(
        "weights", "fetch --endpoint 'not a url'", ["weights", "fetch", "ViT-B-32", "openai", "--endpoint", "not a url"]
    )
    case(
        "weights",
        "fetch --endpoint ftp://127.0.0.1:1",
        ["weights", "fetch", "ViT-B-32", "openai", "--endpoint", "ftp://127.0.0.1:1"],
    )
    case("weights", "fetch an unknown model", ["weights", "fetch", "ViT-Z-99", "openai"])
    # batch
    case("batch", "--out is a file", ["batch", str(p / "photo.png"), "--out", str(p / "a_file")])
    case("batch", "an input that does not exist", ["batch", str(p / "nothing"), "--out", "{OUT}"])
    (p / "emptydir").mkdir()
    case("batch", "an empty input folder", ["batch", str(p / "emptydir"), "--out", "{OUT}"])
    case("batch", "--steps unknown", ["batch", str(p / "photo.png"), "--out", "{OUT}", "--steps", "fly"])
    return cases


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=ROOT_DIR / "docs" / "benchmarks")
    args = parser.parse_args()
    from tqdm import tqdm

    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        elicit = [sys.executable, "-m", "elicit_diffrender.apps.cli"]
        subject, run = root / "subject", root / "run"
        subprocess.run([*elicit, "synth", "--seed", "3", "--size", "64", "--out", str(subject)], check=True,
                       capture_output=True)  # fmt: skip
        subprocess.run([*elicit, "fit", str(subject), "--out", str(run), *SETS], check=True, capture_output=True)
        rows = []
        for cmd, what, argv, out in tqdm(build_cases(root, subject, run), desc="hostile cases", unit="case"):
            before = _snapshot(root, out)
            try:
                done = subprocess.run([sys.executable, "-c", WRAPPER, *argv], capture_output=True, text=True,
                                      cwd=root, timeout=300)  # fmt: skip
                code, err, peak = done.returncode, done.stderr, int((done.stdout.strip().splitlines() or ["0"])[-1])
            except subprocess.TimeoutExpired:
                code, err, peak = "timeout", "", 0
            lines = [line for line in err.splitlines() if line.strip() and "%|" not in line]
            changed = _snapshot(root, out) != before
            clean = (code == 2 and len(lines) == 1) or (code == 0 and "Traceback" not in err)
            rows.append({
                "command": cmd, "input": what, "exit": code, "stderr_lines": len(lines),
                "traceback": "Traceback" in err,
                "peak_mb": peak, "outside_changed": changed, "ok": clean and not changed and peak < 2048,
                "message": (lines[-1] if lines else "")[:160],
            })  # fmt: skip
    passed = sum(r["ok"] for r in rows)
    data = {"cases": rows, "passed": passed, "total": len(rows), "seconds": time.perf_counter() - start,
            "peak_rss_mb_of_this_script": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024}  # fmt: skip
    table = "| command | input | exit | stderr lines | peak MB | ok | message |\n|---|---|---|---|---|---|---|\n"
    for r in rows:
        message = r["message"].replace("|", "/")
        table += (f"| {r['command']} | {r['input']} | {r['exit']} | {r['stderr_lines']} | {r['peak_mb']} | "
                  f"{'yes' if r['ok'] else '**no**'} | {message} |\n")  # fmt: skip
    md = (
        f"# Hostile inputs beyond the tests\n\n{passed} of {len(rows)} cases end cleanly: exit 2 with one stderr "
        f"line, or exit 0 for odd but valid input; no traceback, no file changed outside the case's output folder, "
        f"peak memory under 2 GB.\n\n{table}"
    )
    write_report(args.out, "hostile_sweep", data, md)
    print(md)
    return 0 if passed == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
