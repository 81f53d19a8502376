"""``elicit app``: the page in a real browser (Playwright driving the system's Chromium), its ``/make_avatar`` API
through ``gradio_client``, and the job bookkeeping the page reads."""

import os
import sys
from pathlib import Path
from urllib.parse import urlparse

import httpx
import imageio.v2 as imageio
import pytest
from test_export import validate_glb
from test_fit import TINY as FIT_TINY  # noqa: I001 - the tiny fit settings are shared with the fit tests

from elicit_diffrender.apps.benchtools import app_job_in_page, chromium_page, free_port, start_app, viewer_coverage
from elicit_diffrender.apps.webapp import (
    MAX_UPLOAD_MB,
    PHASES,
    AppError,
    copy_uploads,
    finished_jobs,
    job_progress,
    plain,
    readable,
    run_zip,
)
from elicit_diffrender.core.io import write_json
from elicit_diffrender.data.subject import load_subject
from elicit_diffrender.fit.trainer import PROGRESS_FILE
from elicit_diffrender.inputs.synth import synthesize
from elicit_diffrender.outputs.viewer import glb_problem

TINY = [*FIT_TINY, "init_steps=30", "steps=60", "preview_every=20"]


@pytest.fixture(scope="module")
def photo(tmp_path_factory) -> tuple[Path, Path]:
    """A synthetic subject's input photo and its mask."""
    root = synthesize(11, tmp_path_factory.mktemp("app_photo") / "s", size=256, spp=4, n_cameras=1, texture_size=256)
    subject = load_subject(root)
    return subject.image_path("cam00", 0), subject.mask_path("cam00", 0)


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    """``elicit app`` on a free port with a tiny fit; yields (url, jobs folder). Stopped with SIGTERM, as a service
    manager would; it must end as any command does (exit code 128 + 15), its Ray shut down."""
    out = tmp_path_factory.mktemp("app_jobs")
    port = free_port()
    sets = [x for kv in TINY for x in ("--set", kv)]
    cmd = [sys.executable, "-m", "elicit_diffrender.apps.cli", "app", "--port", str(port), "--out", str(out), *sets]
    url = f"http://127.0.0.1:{port}/"
    server = start_app(cmd, url, out.parent / "app.log")
    yield url, out
    server.terminate()
    assert server.wait(timeout=60) == 128 + 15


@pytest.mark.slow
def test_the_page_makes_an_avatar_in_a_browser(app, photo, tmp_path):
    from playwright.sync_api import sync_playwright

    url, out = app
    requests = []
    with sync_playwright() as playwright:
        page = chromium_page(playwright)
        page.on("request", lambda r: requests.append(r.url))
        job = app_job_in_page(page, url, *photo)
        status = page.locator("#status p").inner_text()
        assert job["phase"] == "done" and "done in" in status, status
        # The bar advanced through the job: several values between 0 and 1, never backwards.
        fractions = job["fractions"]
        assert len([f for f in fractions if 0.0 < f < 1.0]) >= 3 and fractions == sorted(fractions), fractions
        # The 3D viewer shows the avatar: pixels other than the background in the middle of its canvas.
        assert viewer_coverage(page, tmp_path / "viewer.png") > 0.05
        page.screenshot(path=os.environ.get("ELICIT_APP_SCREENSHOT", str(tmp_path / "page.png")), full_page=True)
        # The prepare overlay, the contact sheet and the turntable are on the page.
        for element in ("#overlay img", "#sheet img", "#turntable video"):
            assert page.locator(element).count() == 1, element
        # Download the GLB the way a user does, and validate it.
        with page.expect_download() as download:
            page.locator("#downloads a[download='avatar.glb']").click()
        download.value.save_as(tmp_path / "downloaded.glb")
        validate_glb(tmp_path / "downloaded.glb")
        # A text file named .png: its one-line error in the page, and the app goes on.
        fake = tmp_path / "notes.png"
        fake.write_text("not a photo")
        job = app_job_in_page(page, url, fake, None)
        error = page.locator("#status p").inner_text()
        assert job["phase"] == "failed", job
        assert error.startswith("error: notes.png") and "\n" not in error.strip() and str(out) not in error, error
    # Nothing left this machine: every request went to the app's own address.
    local = [u for u in requests if urlparse(u).scheme in ("blob", "data") or urlparse(u).hostname == "127.0.0.1"]
    assert requests and not sorted(set(requests) - set(local))


@pytest.mark.slow
def test_make_avatar_through_gradio_client(app, photo, tmp_path):
    from gradio_client import Client, handle_file

    url, out = app
    client = Client(url, verbose=False, download_files=str(tmp_path))
    glb, video, sheet = client.predict(
        handle_file(str(photo[0])), handle_file(str(photo[1])), "cpu-fast", api_name="/make_avatar"
    )
    assert glb_problem(Path(glb).read_bytes()) == ""
    video = Path(video["video"] if isinstance(video, dict) else video)
    assert video.suffix == ".mp4" and video.stat().st_size > 1000
    assert imageio.imread(sheet).shape[1] > imageio.imread(sheet).shape[0]  # five tiles side by side
    # Every finished job is listed for reopening (this one, and the browser test's if it ran first).
    assert len(finished_jobs(out)) >= 1
    # Uploads above the limit are refused by the server itself.
    big = tmp_path / "big.png"
    big.write_bytes(bytes(MAX_UPLOAD_MB * 2**20 + 1))
    with big.open("rb") as stream:
        assert httpx.post(f"{url}gradio_api/upload", files={"files": stream}, timeout=60).status_code == 413
    fake = tmp_path / "empty.png"
    fake.write_bytes(b"")
    with pytest.raises(Exception, match="empty.png"):
        client.predict(handle_file(str(fake)), None, "cpu-fast", api_name="/make_avatar")


def test_job_progress_follows_the_files_a_job_writes(tmp_path):
    job = tmp_path / "job"
    job.mkdir()
    assert job_progress(job) == (0.0, "waiting for a free worker")
    write_json(job / "job.json", {"status": "running"})
    assert job_progress(job) == (0.0, "prepare")
    (job / "run").mkdir()
    assert job_progress(job) == (pytest.approx(PHASES["prepare"]), "fit set-up")
    write_json(job / "run" / PROGRESS_FILE, {"stage": 2, "step": 50, "steps": 100})
    before_stage_2 = PHASES["prepare"] + PHASES["fit set-up"] + PHASES["stage 1"]
    assert job_progress(job) == (pytest.approx(before_stage_2 + 0.5 * PHASES["stage 2"]), "stage 2")
    (job / "run" / "avatar.safetensors").write_bytes(b"x")
    assert job_progress(job) == (pytest.approx(before_stage_2 + PHASES["stage 2"]), "render")
    (job / "avatar.glb").write_bytes(b"x")
    assert job_progress(job) == (1.0, "done")
    zipped = run_zip(job)
    assert zipped.is_file() and zipped.stat().st_size > 0


def test_uploads_get_names_the_server_chooses(tmp_path):
    job = tmp_path / "job"
    (job / "inputs").mkdir(parents=True)
    upload = tmp_path / "gradio" / "my photo; rm -rf ~.PNG"
    upload.parent.mkdir(parents=True)
    upload.write_bytes(b"data")
    copies, names = copy_uploads([str(upload)], job, "photo")
    assert copies == [job / "inputs" / "photo_0.png"] and names == ["my photo; rm -rf ~.PNG"]
    masks, mask_names = copy_uploads([str(upload)], job, "mask")
    write_json(job / "job.json", {"status": "failed", "uploads": names, "mask_uploads": mask_names})
    assert readable(f"{copies[0]}: unreadable photo", job) == "my photo; rm -rf ~.PNG: unreadable photo"
    assert readable(f"{masks[0]}: 10x20, the photo 30x40", job) == "my photo; rm -rf ~.PNG: 10x20, the photo 30x40"
    script = tmp_path / "run.sh"
    script.write_text("echo")
    with pytest.raises(AppError, match="run.sh: a photo must be one of"):
        copy_uploads([str(script)], job, "photo")
    assert plain("my_photo (1).png: *bad*") == r"my\_photo \(1\)\.png: \*bad\*"  # shown as is in the page
    # Only finished jobs are listed, by folder name.
    write_json(tmp_path / "a" / "job.json", {"status": "done", "uploads": ["me.jpg"]})
    assert finished_jobs(tmp_path) == [("a  (me.jpg)", "a")]


def test_bad_app_options_give_one_line(tmp_path, capsys):
    from elicit_diffrender.apps.cli import main

    assert main(["app", "--out", str(tmp_path), "--set", "no_such_key=1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("elicit app: error:") and "no_such_key" in err and "\n" not in err
    with pytest.raises(SystemExit) as stop:
        main(["app", "--port", "99999"])
    assert stop.value.code == 2
