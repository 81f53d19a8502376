"""``elicit app``: a local web page (Gradio) from photos of a person to an animated avatar.

A job is ``elicit batch``'s job: the uploads are copied into ``OUT/<job id>/inputs/`` under names the server
chooses, and :func:`~elicit_diffrender.apps.batch.run_job` prepares, fits, renders and exports them in a Ray
task, on an embedded local Ray that runs one job at a time (each asks for all of this machine's CPUs) or on
the cluster at ``--address``. The page follows a job through the files it writes:

    subject/overlay.png     prepare done: the body over the photo
    run/progress.json       the fit's stage and step (``fit/trainer.py``), run/previews/ its preview images
    contact_sheet.png       render done (turntable.mp4 beside it)
    avatar.glb              export done

Finished job folders stay in ``OUT`` and are listed again after a restart. The same action is the API
endpoint ``/make_avatar`` (photo, optional mask, preset -> GLB, turntable video, contact sheet).

Safe by default: it binds 127.0.0.1, makes no share link unless asked, turns Gradio's analytics off, serves
its fonts, scripts and 3D viewer itself, and takes uploads up to ``MAX_UPLOAD_MB``. No path from the client
is used: an upload is read from Gradio's own upload folder and copied under a name chosen here.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import tempfile
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

from ..core.errors import ElicitError
from ..core.io import atomic_write, read_json, write_json
from ..fit.config import PRESETS, config_dict, make_config
from ..fit.trainer import PROGRESS_FILE
from ..model.avatar import AVATAR_FILE
from .batch import JOB_FILE, PHOTO_SUFFIXES, STEPS, Job, finish_task, job_task, read_record, start_ray

MAX_UPLOAD_MB = 25  # per file
RENDER_SIZE = 256  # pixels of the turntable and contact sheet (as ``elicit batch``)
POLL_S = 1.0  # seconds between looks at a running job's folder
# Shares of a job's time, for the progress bar (a cpu-fast job on the demo photo on 2 cores, bench_app.py)
PHASES = {"prepare": 0.20, "fit set-up": 0.07, "stage 1": 0.03, "stage 2": 0.45, "render": 0.20, "export": 0.05}
ZIP_FILE = "run.zip"
VIEWER_BACKGROUND = (0.13, 0.13, 0.13, 1.0)  # RGBA of the 3D viewer's canvas


class AppError(ElicitError):
    """An upload or a setting the app refuses (shown as one line in the page)."""


# ---- jobs on disk ---------------------------------------------------------------------------------------------
def new_job_dir(out: Path) -> Path:
    """A fresh job folder under ``out``, named by the time and a random tag (never by the client)."""
    job_dir = out / f"{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(3)}"
    (job_dir / "inputs").mkdir(parents=True)
    return job_dir


def copy_uploads(paths: list[str], job_dir: Path, kind: str) -> tuple[list[Path], list[str]]:
    """Copy uploaded files (paths inside Gradio's upload folder) to ``job_dir/inputs/<kind>_<k><suffix>``;
    returns the copies and the names the user gave them. Only the suffix of a name is kept, and only a photo's."""
    copies, names = [], []
    for k, path in enumerate(paths):
        source = Path(path)
        suffix = source.suffix.lower()
        if suffix not in PHOTO_SUFFIXES:
            raise AppError(f"{source.name}: a {kind} must be one of {', '.join(PHOTO_SUFFIXES)}")
        copy = job_dir / "inputs" / f"{kind}_{k}{suffix}"
        shutil.copyfile(source, copy)
        copies.append(copy)
        names.append(source.name)
    return copies, names


def fit_settings(preset: str, text: str, launch: list[str]) -> dict:
    """The fit's configuration: the preset, the page's ``key=value`` lines, then the launch's ``--set`` values
    (which apply to every job)."""
    lines = [line.strip() for line in (text or "").splitlines() if line.strip() and not line.strip().startswith("#")]
    return config_dict(make_config(preset, None, lines + list(launch)))


def job_progress(job_dir: Path) -> tuple[float, str]:
    """How far a job is (0-1) and what it does now, read from the files it has written."""
    run = job_dir / "run"
    done = 0.0
    if (job_dir / "avatar.glb").is_file():
        return 1.0, "done"
    if (job_dir / "contact_sheet.png").is_file():
        phase, within = "export", 0.0
    elif (run / AVATAR_FILE).is_file():
        phase, within = "render", 0.0
    elif (run / PROGRESS_FILE).is_file():
        try:
            state = read_json(run / PROGRESS_FILE)
            phase, within = f"stage {int(state['stage'])}", int(state["step"]) / max(1, int(state["steps"]))
        except (ElicitError, KeyError, TypeError, ValueError):
            phase, within = "fit set-up", 1.0
    elif run.is_dir() or (job_dir / "subject" / "subject.json").is_file():
        phase, within = "fit set-up", 0.0
    elif read_record(job_dir).get("status") == "running":
        phase, within = "prepare", 0.0
    else:
        return 0.0, "waiting for a free worker"
    for name, share in PHASES.items():
        if name == phase:
            return done + share * min(max(within, 0.0), 1.0), phase
        done += share
    return done, phase


def latest_preview(job_dir: Path) -> Path | None:
    """The fit's newest preview image (input view: target | render, then ring views), if any."""
    previews = sorted((job_dir / "run" / "previews").glob("*.png"), key=lambda p: (p.stat().st_mtime_ns, p.name))
    return previews[-1] if previews else None


def run_zip(job_dir: Path) -> Path:
    """``job_dir/run.zip``: the run folder (avatar, checkpoint, previews, logs), written once."""
    path = job_dir / ZIP_FILE
    if not path.is_file():

        def write(tmp: Path) -> None:
            with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as archive:
                for file in sorted((job_dir / "run").rglob("*")):
                    if file.is_file() and not file.name.startswith("."):
                        archive.write(file, Path("run") / file.relative_to(job_dir / "run"))

        atomic_write(path, write)
    return path


def _existing(path: Path | None) -> str | None:
    return str(path) if path is not None and path.is_file() else None


def live_images(job_dir: Path) -> dict[str, str | None]:
    """What a running job shows so far: the prepare overlay and the fit's newest preview (None until written)."""
    return {"overlay": _existing(job_dir / "subject" / "overlay.png"), "preview": _existing(latest_preview(job_dir))}


def results(job_dir: Path) -> dict[str, str | list[str] | None]:
    """A job's files that the page shows (None where a step did not write one); zips its run folder for download."""
    downloads = [job_dir / "avatar.glb", job_dir / "run" / AVATAR_FILE]
    if (job_dir / "run" / AVATAR_FILE).is_file():
        downloads.append(run_zip(job_dir))
    return {
        **live_images(job_dir),
        "glb": _existing(job_dir / "avatar.glb"),
        "video": _existing(job_dir / "turntable.mp4"),
        "sheet": _existing(job_dir / "contact_sheet.png"),
        "downloads": [str(p) for p in downloads if p.is_file()],
    }


def finished_jobs(out: Path) -> list[tuple[str, str]]:
    """(label, folder name) of every finished job under ``out``, newest first."""
    rows = []
    for job_dir in sorted((p for p in out.iterdir() if (p / JOB_FILE).is_file()), reverse=True):
        record = read_record(job_dir)
        if record.get("status") == "done":
            photos = ", ".join(record.get("uploads", [])) or record.get("source", "")
            rows.append((f"{job_dir.name}  ({photos})", job_dir.name))
    return rows


# ---- running a job ------------------------------------------------------------------------------------------
class JobRunner:
    """Submits jobs to Ray (started once, for the app's life) and follows them through their folders."""

    def __init__(self, out: Path, launch_settings: list[str], cpus_per_fit: int) -> None:
        self.out, self.launch_settings, self.cpus_per_fit = out, list(launch_settings), cpus_per_fit

    def start(self, photos: list[str], masks: list[str], preset: str, settings: str) -> tuple[Path, object]:
        """Check the inputs, copy them into a new job folder and submit the job; returns the folder and the task."""
        if not photos:
            raise AppError("no photo: upload one or more photos of one person")
        if masks and len(masks) != len(photos):
            raise AppError(f"{len(masks)} masks for {len(photos)} photos: give one mask per photo, or none")
        config = fit_settings(preset, settings, self.launch_settings)
        job_dir = new_job_dir(self.out)
        try:
            photo_copies, names = copy_uploads(photos, job_dir, "photo")
            mask_copies, mask_names = copy_uploads(masks, job_dir, "mask") if masks else ([None] * len(photos), [])
        except (AppError, OSError):
            shutil.rmtree(job_dir, ignore_errors=True)  # a refused upload leaves no job behind
            raise
        job = Job(job_dir.name, job_dir / "inputs", tuple(photo_copies), tuple(mask_copies))
        record = {"status": "queued", "uploads": names, "mask_uploads": mask_names, "preset": preset}
        write_json(job_dir / JOB_FILE, record)
        return job_dir, job_task(self.cpus_per_fit).remote(job, job_dir, STEPS, config, RENDER_SIZE)

    def follow(self, job_dir: Path, task) -> Iterator[tuple[float, str, dict]]:
        """(progress, phase, record) every ``POLL_S`` until the task ends; the last one has the job's record."""
        import ray

        while True:
            ready, _ = ray.wait([task], timeout=POLL_S)
            if ready:
                record = finish_task(task, job_dir)
                yield (1.0, "done", record) if record.get("status") == "done" else (0.0, "failed", record)
                return
            fraction, phase = job_progress(job_dir)
            yield fraction, phase, {}


def readable(error: str, job_dir: Path) -> str:
    """A job's error line with the server's paths replaced by the names the user gave the files."""
    record = read_record(job_dir)
    for kind, key in (("photo", "uploads"), ("mask", "mask_uploads")):
        for k, name in enumerate(record.get(key, [])):
            for copy in (job_dir / "inputs").glob(f"{kind}_{k}.*"):
                error = error.replace(str(copy), name)
    return error.replace(str(job_dir), "job")


def plain(text: str) -> str:
    """``text`` shown as is in Markdown (a file name may hold ``*``, ``_`` or ``<``)."""
    return re.sub(r"([\\`*_{}\[\]<>()#+\-.!|~])", r"\\\1", " ".join(text.split()))


def progress_html(fraction: float, phase: str) -> str:
    percent = round(100 * fraction)
    return (
        f'<div id="job-progress" data-fraction="{fraction:.4f}" data-phase="{phase}">'
        f'<progress value="{fraction:.4f}" max="1" style="width:100%"></progress> {percent}% &middot; {phase}</div>'
    )


# ---- the page ---------------------------------------------------------------------------------------------
def build_page(runner: JobRunner, default_preset: str):
    """The Gradio page and its ``/make_avatar`` endpoint."""
    import gradio as gr

    out = runner.out

    def job_choices():
        return gr.update(choices=finished_jobs(out))

    def shown(job_dir: Path, status: str) -> dict:
        files = results(job_dir)
        return {
            status_box: status,
            bar: progress_html(1.0, "done"),
            overlay: files["overlay"],
            preview: files["preview"],
            viewer: files["glb"],
            video: files["video"],
            sheet: files["sheet"],
            downloads: files["downloads"] or None,
            jobs: job_choices(),
        }

    def make(photos, masks, preset, settings):
        """The page's action: one job, with progress and the fit's preview as it trains."""
        try:
            job_dir, task = runner.start(list(photos or []), list(masks or []), preset, settings)
        except (ElicitError, OSError) as exc:
            yield {
                status_box: f"**error:** {plain(str(exc))}",
                bar: progress_html(0.0, "not started"),
                current: "",
            }
            return
        t0 = time.perf_counter()
        yield {status_box: f"job `{job_dir.name}` queued", bar: progress_html(0.0, "queued"), current: job_dir.name}
        last = {}
        for fraction, phase, record in runner.follow(job_dir, task):
            if phase == "failed":
                line = readable(str(record.get("error") or "the job failed"), job_dir)
                yield {status_box: f"**error:** {plain(line)}", bar: progress_html(0.0, "failed")}
                return
            if phase == "done":  # the results are shown by ``show_done`` (a Model3D set by a generator stays blank)
                yield {status_box: f"job `{job_dir.name}` done in {time.perf_counter() - t0:.0f} s"}
                return
            update = {bar: progress_html(fraction, phase)}
            files = live_images(job_dir) if phase not in ("prepare", "waiting for a free worker") else {}
            for key, component in (("overlay", overlay), ("preview", preview)):
                if files.get(key) and files[key] != last.get(key):
                    update[component] = last[key] = files[key]
            yield update

    def show_done(name, status):
        job_dir = out / name if name else None
        if job_dir is None or read_record(job_dir).get("status") != "done":
            return {}
        return shown(job_dir, status)

    def open_job(name):
        if not name:
            return {status_box: "choose a finished job"}
        if name not in [folder for _, folder in finished_jobs(out)]:  # a name from the list, never a path
            return {status_box: f"**error:** no finished job {name!r}"}
        job_dir = out / name
        return shown(job_dir, f"job `{job_dir.name}`")

    def make_avatar(photo, mask, preset):
        """One photo (and optionally its mask) of a person to an avatar: the GLB, the turntable video and the
        contact sheet."""
        try:
            job_dir, task = runner.start([photo] if photo else [], [mask] if mask else [], preset or default_preset, "")
        except (ElicitError, OSError) as exc:
            raise gr.Error(" ".join(str(exc).split())) from None
        *_, (_, phase, record) = runner.follow(job_dir, task)
        if phase != "done":
            raise gr.Error(readable(str(record.get("error") or "the job failed"), job_dir))
        files = results(job_dir)
        return files["glb"], files["video"], files["sheet"]

    with gr.Blocks(title="elicit: photo to avatar", analytics_enabled=False) as page:
        gr.Markdown("# elicit: photos of a person to an animatable avatar")
        with gr.Row():
            with gr.Column(scale=1):
                photos = gr.File(
                    label="photos of one person", file_count="multiple", file_types=["image"], elem_id="photos"
                )
                masks = gr.File(
                    label="masks (optional: one per photo, in the same order)",
                    file_count="multiple",
                    file_types=["image"],
                    elem_id="masks",
                )
                preset = gr.Dropdown(list(PRESETS), value=default_preset, label="preset", elem_id="preset")
                with gr.Accordion("advanced: fit keys", open=False):
                    settings = gr.Textbox(
                        label="one key=value per line (see `elicit fit --help`)",
                        lines=3,
                        placeholder="steps=3000\nseed=0",
                        elem_id="settings",
                    )
                start = gr.Button("make avatar", variant="primary", elem_id="start")
                bar = gr.HTML(progress_html(0.0, "idle"), elem_id="bar")
                status_box = gr.Markdown("", elem_id="status")
                jobs = gr.Dropdown(label="finished jobs", choices=[], elem_id="jobs")
                open_button = gr.Button("open job", elem_id="open")
            with gr.Column(scale=3):
                with gr.Row():
                    overlay = gr.Image(label="body fit over the photo", type="filepath", elem_id="overlay", scale=1)
                    viewer = gr.Model3D(
                        label="avatar", clear_color=VIEWER_BACKGROUND, elem_id="viewer", height=480, scale=2
                    )
                preview = gr.Image(label="fit preview: input | render, ring views", type="filepath", elem_id="preview")
                with gr.Row():
                    video = gr.Video(label="turntable", elem_id="turntable", scale=1)
                    sheet = gr.Image(label="contact sheet", type="filepath", elem_id="sheet", scale=2)
                downloads = gr.File(label="downloads", file_count="multiple", elem_id="downloads")
        current = gr.State("")  # the folder name of the page's latest job
        outputs = [status_box, bar, overlay, preview, viewer, video, sheet, downloads, jobs]
        start.click(
            make,
            [photos, masks, preset, settings],
            [status_box, bar, overlay, preview, current],
            concurrency_limit=None,
            api_visibility="private",
            show_progress="hidden",  # the job's own bar shows it
        ).then(show_done, [current, status_box], outputs, api_visibility="private")
        open_button.click(open_job, [jobs], outputs, api_visibility="private")
        page.load(job_choices, None, [jobs], api_visibility="private")
        # The API's own components: one photo, its mask, a preset -> GLB, turntable, contact sheet.
        with gr.Row(visible=False):
            api_in = [gr.File(label="photo"), gr.File(label="mask"), gr.Textbox(label="preset", value=default_preset)]
            api_out = [
                gr.File(label="avatar.glb"),
                gr.Video(label="turntable"),
                gr.Image(label="contact sheet", type="filepath"),
            ]
            api_button = gr.Button("make_avatar")
        api_button.click(make_avatar, api_in, api_out, api_name="make_avatar", concurrency_limit=None)
    return page


def serve(
    out: Path,
    host: str = "127.0.0.1",
    port: int = 7860,
    preset: str = "cpu-fast",
    settings: list[str] | None = None,
    address: str | None = None,
    cpus_per_fit: int | None = None,
    share: bool = False,
) -> None:
    """Start Ray and the page, and serve until interrupted; Ray is shut down however it ends."""
    os.environ["GRADIO_ANALYTICS_ENABLED"] = "False"  # before Gradio is imported: no telemetry, no version check
    import ray

    from ..core.device import cpus_given

    fit_settings(preset, "", settings or [])  # a bad --preset or --set stops here, with one line
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    runner = JobRunner(out, settings or [], cpus_per_fit or (1 if address else cpus_given()))
    with tempfile.TemporaryDirectory() as stage:
        start_ray(address, Path(stage))
        try:
            page = build_page(runner, preset)
            page.queue(default_concurrency_limit=None)
            page.launch(
                server_name=host,
                server_port=port,
                share=share,
                allowed_paths=[str(out)],
                max_file_size=f"{MAX_UPLOAD_MB}mb",
                show_error=True,
                quiet=True,
                prevent_thread_lock=True,
            )
            print(f"elicit app: serving {page.local_url}" + (f" and {page.share_url}" if share else ""), flush=True)
            print(f"elicit app: jobs in {out}; Ctrl-C stops", flush=True)
            page.block_thread()
        finally:
            ray.shutdown()
