"""Hostile and careless inputs, as an attacker or a tired user hands them in: every case ends with exit code 2 and one
line on stderr, changes no file outside its output folder and stays under 2 GB of memory. Each test makes its own
payload."""

from __future__ import annotations

import json
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

MEMORY_LIMIT_MB = 2048
# Runs the command line in a child and reports the child's peak memory: the last stdout line of this wrapper.
WRAPPER = (
    "import resource, subprocess, sys; "
    "done = subprocess.run([sys.executable, '-m', 'elicit_diffrender.apps.cli', *sys.argv[1:]]); "
    "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss // 1024); sys.exit(done.returncode)"
)


def _tree(root: Path, skip: Path | None) -> dict[str, tuple[int, int]]:
    """Every file under ``root`` but ``skip`` (its size and modification time), to see what a command changed."""
    out = {}
    for path in sorted(root.rglob("*")):
        if skip is not None and (path == skip or skip in path.parents):
            continue
        if path.is_file() and not path.is_symlink():
            info = path.stat()
            out[str(path)] = (info.st_size, info.st_mtime_ns)
    return out


def hostile(tmp_path: Path, *args: str, out: Path | None = None, expect: str = "", progress: bool = False) -> str:
    """Run ``elicit ARGS``; check exit code 2, one stderr line (containing ``expect``; after a progress bar's lines
    with ``progress``), no change under ``tmp_path`` outside ``out``, and peak memory under the limit; returns the
    line."""
    before = _tree(tmp_path, out)
    done = subprocess.run([sys.executable, "-c", WRAPPER, *args], capture_output=True, text=True, cwd=tmp_path)
    lines = [line for line in done.stderr.strip().splitlines() if not (progress and ("%|" in line or not line.strip()))]
    assert done.returncode == 2, done.stderr[-3000:]
    assert len(lines) == 1 and lines[0].startswith("elicit ") and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert expect in lines[0], lines[0]
    assert _tree(tmp_path, out) == before, "files changed outside the output folder"
    peak = int(done.stdout.strip().splitlines()[-1])
    assert peak < MEMORY_LIMIT_MB, f"peak memory {peak} MB"
    return lines[0]


def _image(path: Path, size: int = 64) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((size, size, 3), 128, dtype=np.uint8)).save(path, format="PNG")
    return path


def _mask(path: Path, size: int = 64) -> Path:
    m = np.zeros((size, size), dtype=np.uint8)
    m[8:56, 20:44] = 255
    Image.fromarray(m).save(path)
    return path


def _wild(folder: Path) -> Path:
    """A minimal ELICIT in-the-wild folder (image, mask, CLIFF parameters)."""
    _image(folder / "gt_image.png")
    _mask(folder / "gt_mask.png")
    np.savez(folder / "gt_params.npz", pose=np.zeros((1, 72)), shape=np.zeros((1, 10)),
             global_t=np.array([[0.0, 0.0, 3.0]]), focal_l=np.array(500.0))  # fmt: skip
    return folder


class _ForgedDtype:
    """Pickles as an object dtype whose state zeroes its flags (numpy then builds objects from raw bytes)."""

    def __reduce__(self):
        return (np.dtype, ("O8", False, True), (3, "|", None, None, None, -1, -1, 0))


class _ForgedArray:
    def __reduce__(self):
        from numpy._core.multiarray import _reconstruct

        return (_reconstruct, (np.ndarray, (0,), b"b"), (1, (2,), _ForgedDtype(), False, b"A" * 16))


def _nested(depth: int) -> list:
    """A list of two references to one list of two references ...: 2**depth leaves, a few bytes as a pickle."""
    a: list = []
    for _ in range(depth):
        a = [a, a]
    return a


# ---- 1. names from data never become paths outside their folder ----


@pytest.fixture(scope="module")
def tiny_subject(tmp_path_factory):
    from elicit_diffrender.inputs.synth import synthesize

    return synthesize(5, tmp_path_factory.mktemp("tiny") / "s", "rest", size=48, spp=1, n_cameras=2, texture_size=64)


def _copy_subject(src: Path, dest: Path) -> Path:
    import shutil

    shutil.copytree(src, dest)
    return dest


@pytest.mark.parametrize("name", ["../../outside", "/etc", "cam/../../x", ".."])
def test_camera_names_that_leave_the_subject_are_refused(tmp_path, tiny_subject, name):
    subject = _copy_subject(tiny_subject, tmp_path / "s")
    cams = json.loads((subject / "cameras.json").read_text())
    cams[name] = cams.pop("cam01")
    (subject / "cameras.json").write_text(json.dumps(cams))
    hostile(tmp_path, "fit", str(subject), "--out", str(tmp_path / "run"), out=tmp_path / "run",
            expect="is not a plain name")  # fmt: skip


def test_zju_image_paths_that_leave_the_folder_are_refused(tmp_path, smpl_file):
    src = tmp_path / "zju"
    (src / "new_params").mkdir(parents=True)
    np.save(src / "new_params" / "0.npy", np.array({"shapes": np.zeros((1, 10)), "poses": np.zeros((1, 72)),
            "Rh": np.zeros((1, 3)), "Th": np.zeros((1, 3))}, dtype=object), allow_pickle=True)  # fmt: skip
    _image(tmp_path / "secret.jpg")
    cams = {"K": [np.eye(3)], "R": [np.eye(3)], "T": [np.zeros((3, 1))]}
    annots = {"cams": cams, "ims": [{"ims": ["../secret.jpg"]}]}
    np.save(src / "annots.npy", np.array(annots, dtype=object), allow_pickle=True)
    hostile(tmp_path, "import", "zju", str(src), "--frames", "0", "--smpl", str(smpl_file), "--out",
            str(tmp_path / "out"), out=tmp_path / "out", expect="leads outside")  # fmt: skip


def test_a_model_path_that_is_no_model_file_is_refused(tmp_path):
    from elicit_diffrender.body import BodyModelError, load_body

    (tmp_path / "notes.txt").write_text("not a model")
    with pytest.raises(BodyModelError, match="not a model file"):
        load_body({"model": "smpl", "betas": [0.0] * 10, "model_path": str(tmp_path / "notes.txt")})
    with pytest.raises(BodyModelError, match="must be a path"):
        load_body({"model": "smpl", "betas": [0.0] * 10, "model_path": ["/etc/hostname"]})


@pytest.mark.slow
def test_a_batch_photo_named_dot_dot_stays_inside_out(tmp_path):
    from elicit_diffrender.apps.batch import find_jobs, job_name

    inputs = tmp_path / "in"
    _image(inputs / "...png")
    victim = tmp_path / "subject"
    victim.mkdir()
    (victim / "mine.txt").write_text("keep me")
    assert [j.name for j in find_jobs([inputs])] == ["job"] and job_name("a/b") == "a_b" and job_name("..") == "job"
    out = tmp_path / "out"
    hostile(tmp_path, "batch", str(inputs), "--out", str(out), "--steps", "prepare", out=out, expect="failed",
            progress=True)  # fmt: skip
    assert (victim / "mine.txt").read_text() == "keep me" and (out / "job" / "job.json").is_file()


# ---- 2. pickles that would crash or run code ----


def test_a_forged_numpy_dtype_is_refused_not_a_segfault(tmp_path):
    forged = tmp_path / "forged.pkl"
    forged.write_bytes(pickle.dumps({"v_template": _ForgedArray()}, protocol=2))
    hostile(tmp_path, "import", "elicit-wild", str(_wild(tmp_path / "wild")), "--smpl", str(forged),
            "--out", str(tmp_path / "out"), out=tmp_path / "out", expect="refused")  # fmt: skip


@pytest.mark.parametrize(
    "ref", [b"scipy.sparse\nnot_there", b"scipy.sparse.not_there\ncsc_matrix", b"scipy.sparse.csc.x\ncsr_matrix"]
)
def test_a_missing_scipy_sparse_name_is_one_line(tmp_path, ref):
    """A whitelisted matrix name in a scipy.sparse module that does not exist gave a ModuleNotFoundError."""
    pkl = tmp_path / "missing.pkl"
    pkl.write_bytes(b"\x80\x02c" + ref + b"\nq\x00.")
    hostile(tmp_path, "import", "elicit-wild", str(_wild(tmp_path / "wild")), "--smpl", str(pkl),
            "--out", str(tmp_path / "out"), out=tmp_path / "out", expect="missing.pkl")  # fmt: skip


# ---- 3. tiny files that unfold into gigabytes ----


def test_a_zju_annots_file_of_nested_shared_lists_is_bounded(tmp_path):
    src = tmp_path / "zju"
    src.mkdir()
    np.save(src / "annots.npy", np.array({"cams": {}, "ims": _nested(40)}, dtype=object), allow_pickle=True)
    assert (src / "annots.npy").stat().st_size < 4096
    hostile(tmp_path, "import", "zju", str(src), "--frames", "0", "--out", str(tmp_path / "out"),
            out=tmp_path / "out", expect="unfolds to more than")  # fmt: skip


def test_a_smpl_pickle_of_nested_shared_lists_is_bounded(tmp_path):
    pkl = tmp_path / "bomb.pkl"
    pkl.write_bytes(pickle.dumps({"v_template": _nested(40)}, protocol=2))
    assert pkl.stat().st_size < 4096
    hostile(tmp_path, "import", "elicit-wild", str(_wild(tmp_path / "wild")), "--smpl", str(pkl),
            "--out", str(tmp_path / "out"), out=tmp_path / "out", expect="unfolds to more than")  # fmt: skip


# ---- 7. files and values that used to end in a traceback ----


@pytest.mark.parametrize(
    ("name", "text", "expect"),
    [
        ("deep", "[" * 100000 + "]" * 100000, "nested too deep"),
        ("big integer", '{"format": ' + "9" * 5000 + "}", "not valid JSON"),
        ("invalid utf-8", b'{"format": "\xff\xfe"}', "not UTF-8"),
        (
            "camera as a list",
            '{"format": "elicit-subject/1", "body": {"model": "anny"}, "input": {"camera": ["cam00"], "frame": 0}}',
            "field 'input'",
        ),
    ],
)
def test_broken_subject_json_is_one_line(tmp_path, tiny_subject, name, text, expect):
    subject = _copy_subject(tiny_subject, tmp_path / "s")
    target = subject / "subject.json"
    target.write_bytes(text if isinstance(text, bytes) else text.encode())
    hostile(tmp_path, "fit", str(subject), "--out", str(tmp_path / "run"), out=tmp_path / "run", expect=expect)


def test_eval_with_a_malformed_run_json_is_one_line(tmp_path, tiny_subject):
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text('{"subject": ')
    hostile(tmp_path, "eval", str(run), str(tiny_subject), "--out", str(tmp_path / "m" / "m.json"),
            out=tmp_path / "m", expect="run.json")  # fmt: skip


def test_a_batch_input_that_is_a_symbolic_link_loop_is_one_line(tmp_path):
    loop = tmp_path / "loop"
    loop.symlink_to(tmp_path / "loop")
    hostile(tmp_path, "batch", str(loop), "--out", str(tmp_path / "out"), out=tmp_path / "out")


def test_rig_files_and_numbers_that_imply_no_camera_or_endless_work_are_one_line(tmp_path):
    rig = tmp_path / "rig.xml"
    sensor = '<scene version="3.0.0"><sensor type="perspective" id="c">{}<transform name="to_world">{}</transform>' \
             '<film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/></film>' \
             "</sensor></scene>"  # fmt: skip
    cases = [
        ('<float name="fov" value="0"/>', '<lookat origin="0 0 3" target="0 0 0" up="0 1 0"/>', "fov must be"),
        ('<float name="fov" value="nan"/>', '<lookat origin="0 0 3" target="0 0 0" up="0 1 0"/>', "fov must be"),
        ('<float name="fov" value="40"/>', '<scale value="abc"/>', "not a number"),
        ('<float name="fov" value="40"/>', '<lookat origin="1 1 1" target="1 1 1" up="0 1 0"/>', "same point"),
        ('<float name="fov" value="40"/>', '<matrix value="nan 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"/>', "not finite"),
    ]
    out = tmp_path / "out"
    for fov, transform, expect in cases:
        rig.write_text(sensor.format(fov, transform))
        hostile(tmp_path, "render", str(tmp_path / "no-run"), "--cameras", str(rig), "--out", str(out / "v.mp4"),
                out=out, expect="")  # the run is missing too: the first problem found is reported  # fmt: skip
        from elicit_diffrender.data.rigs import RigError, read_rig

        with pytest.raises(RigError, match=expect):
            read_rig(rig)
    for args, expect in [
        (["rig", "ring", "--out", str(out / "r.xml"), "--elevation", "90"], "--elevation"),
        (["rig", "ring", "--out", str(out / "r.xml"), "--elevation", "nan"], "--elevation"),
        (["rig", "orbit", "--out", str(out / "r.xml"), "--look-at", "inf", "0", "0"], "--look-at"),
        (["rig", "ring", "--out", str(out / "r.xml"), "--radius", "1e308"], "--radius"),
        (["synth", "--seed", "-1", "--out", str(out / "s")], "--seed"),
        (["synth", "--seed", str(2**70), "--out", str(out / "s")], "--seed"),
        (["render", "run", "--out", str(out / "v.mp4"), "--fps", "1e-300"], "--fps"),
        (["render", "run", "--out", str(out / "v.mp4"), "--samples", "100000000"], "--samples"),
        (["export", "run", "--out", str(out / "a.glb"), "--resolution", "1e-9"], "--resolution"),
        (["fit", "s", "--out", str(out / "r"), "--set", "w_mse=nan"], "w_mse must be a finite number"),
        (["fit", "s", "--out", str(out / "r"), "--set", "lr=inf"], "lr must be a finite number"),
        (["fit", "s", "--out", str(out / "r"), "--set", "seed=-1"], "seed must be in"),
    ]:
        hostile(tmp_path, *args, out=out, expect=expect)


def test_a_png_that_claims_ten_billion_pixels_is_one_line(tmp_path):
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", 100000, 100000, 8, 2, 0, 0, 0)
    photo = tmp_path / "bomb.png"
    photo.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                      + chunk(b"IEND", b""))  # fmt: skip
    hostile(tmp_path, "prepare", str(photo), "--out", str(tmp_path / "out"), out=tmp_path / "out",
            expect="100000x100000")  # fmt: skip


def test_an_exif_rotated_photo_is_read_upright(tmp_path):
    from elicit_diffrender.core.checks import read_image

    pixels = np.zeros((40, 20, 3), dtype=np.uint8)  # portrait: 20 wide, 40 high, the top row white
    pixels[0] = 255
    stored = Image.fromarray(np.rot90(pixels, 1).copy())  # stored on its side, as a camera held upright writes it
    exif = stored.getexif()
    exif[0x0112] = 6  # Orientation: rotate 90 degrees clockwise to view
    stored.save(tmp_path / "photo.jpg", exif=exif, quality=95)
    rgb, _ = read_image(tmp_path / "photo.jpg", "photo")
    assert rgb.shape[:2] == (40, 20) and rgb[0].mean() > 0.9 and rgb[-1].mean() < 0.1


def test_a_full_disk_names_the_file_it_was_writing(tmp_path, tiny_subject):
    """A fit whose checkpoint cannot be written (a file-size limit stands for a full disk) stops with one line
    naming the checkpoint, and leaves no half-written file."""
    import resource
    import signal

    run = tmp_path / "run"

    def small_files():  # in the child: files above 64 kB cannot grow (EFBIG), as on a full disk
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, 64 * 1024))

    args = ["fit", str(tiny_subject), "--out", str(run), "--set", "init_steps=2", "--set", "steps=2",
            "--set", "checkpoint_every=1", "--set", "preview_every=1000"]  # fmt: skip
    for verbose in ([], ["--verbose"]):
        done = subprocess.run([sys.executable, "-m", "elicit_diffrender.apps.cli", *verbose, *args],
                              capture_output=True, text=True, preexec_fn=small_files)  # fmt: skip
        lines = [line for line in done.stderr.splitlines() if line.strip() and "%|" not in line]
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
        assert "cannot write" in lines[-1] and "checkpoint.safetensors" in lines[-1], lines[-1]
        assert not list(run.glob(".checkpoint.safetensors.*"))
        # Warp's no-GPU banner and the fit's log lines printed before the error; only --verbose shows them.
        assert len(lines) == 1 if not verbose else "thread pools sized" in done.stderr, done.stderr[-2000:]
        shutil.rmtree(run)


def test_a_second_fit_into_a_running_fits_folder_is_refused(tmp_path, tiny_subject):
    import time

    run = tmp_path / "run"
    first = subprocess.Popen([sys.executable, "-m", "elicit_diffrender.apps.cli", "fit", str(tiny_subject), "--out",
                              str(run), "--set", "init_steps=5", "--set", "steps=400"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        for _ in range(600):  # until the first fit holds the folder and has written its log
            if (run / "log.txt").is_file() and (run / ".lock").read_text().strip() == str(first.pid):
                break
            time.sleep(0.1)
        log = (run / "log.txt").read_text()
        done = subprocess.run([sys.executable, "-m", "elicit_diffrender.apps.cli", "fit", str(tiny_subject), "--out",
                               str(run), "--force"], capture_output=True, text=True)  # fmt: skip
        line = done.stderr.strip().splitlines()
        assert done.returncode == 2 and len(line) == 1 and f"process {first.pid}" in line[0], done.stderr[-2000:]
        assert (run / "log.txt").read_text().startswith(log[:200])  # the running fit's log is still there
    finally:
        first.terminate()
        first.wait(timeout=60)


def test_resume_without_a_checkpoint_stops_at_once(tmp_path, tiny_subject):
    import time

    start = time.perf_counter()
    hostile(tmp_path, "fit", str(tiny_subject), "--out", str(tmp_path / "run"), "--resume", out=tmp_path / "run",
            expect="nothing to resume")  # fmt: skip
    assert time.perf_counter() - start < 30


def test_sigterm_leaves_no_half_written_folder(tmp_path):
    import signal
    import time

    out = tmp_path / "s"
    child = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "elicit_diffrender.apps.cli",
            "synth",
            "--seed",
            "3",
            "--out",
            str(out),
            "--size",
            "256",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    for _ in range(600):  # until it writes into its temporary folder
        if list(tmp_path.glob(".s.*.partial")):
            break
        time.sleep(0.1)
    time.sleep(1.0)
    child.send_signal(signal.SIGTERM)
    child.wait(timeout=60)
    assert child.returncode != 0 and not list(tmp_path.glob(".s.*")) and not out.exists()


def test_a_glb_with_its_magic_and_junk_behind_is_refused(tmp_path):
    """``view`` wrote a page around any file that began with ``glTF``."""
    (tmp_path / "junk.glb").write_bytes(b"glTF" + bytes(range(200)))
    out = tmp_path / "out"
    hostile(tmp_path, "view", str(tmp_path / "junk.glb"), "--out", str(out), out=out, expect="not a GLB file")


def test_a_weights_file_that_is_a_pickle_is_one_line(tmp_path, tiny_subject):
    """``clip_pretrained`` naming a pickle: torch's weights-only refusal spans several lines."""
    (tmp_path / "weights.pt").write_bytes(pickle.dumps({"a": print}))
    out = tmp_path / "run"
    args = ["fit", str(tiny_subject), "--out", str(out), "--set", "encoder=clip", "--set", "init_steps=1"]
    args += ["--set", "voxel_size=0.03", "--set", "weight_grid=16"]  # the set-up small: ViT-B-32 alone is 0.6 GB
    line = hostile(tmp_path, *args, "--set", f"clip_pretrained={tmp_path / 'weights.pt'}", out=out, progress=True)
    assert "weights.pt" in line, line
