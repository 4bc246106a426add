"""`rllock serve` against a real server on loopback: every endpoint, the bad inputs, a cancel, the client
limit, batched network evaluation across concurrent generate jobs, a restart that keeps finished jobs,
and the web page in headless Chromium (upload, live progress, the 3D view, the slider, the zip)."""

from __future__ import annotations

import io
import json
import os
import socket
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import requests

from rllock.orchestration.bench.serve import ServerProcess

pytestmark = [pytest.mark.slow, pytest.mark.ray]
RAY_GROUP = "service"  # tests/conftest.py: beside the other Ray tests, on whichever worker is free
CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
LIMITS = [
    "--max-jobs",
    "2",
    "--max-client-jobs",
    "5",
    "--max-upload-mb",
    "0.5",
    "--max-voxels",
    "5000",
    "--max-time-limit",
    "120",
]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    server = ServerProcess(tmp_path_factory.mktemp("serve") / "data", LIMITS)
    try:
        server.start()
        yield server
    finally:
        server.stop()


def test_free_ports_are_free_and_below_the_ones_port_0_binds_get():
    from rllock.orchestration.bench.serve import _ephemeral_low, free_port

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        ephemeral = s.getsockname()[1]
    assert ephemeral >= _ephemeral_low()
    ports = {free_port() for _ in range(20)}
    assert len(ports) > 1 and all(10_000 <= p < _ephemeral_low() for p in ports)
    for port in ports:
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))  # free: binding it again here succeeds


def _box_stl(extents=(3.0, 2.0, 1.5)) -> bytes:
    import trimesh

    return trimesh.creation.box(extents=extents).export(file_type="stl")


def _flat_stl() -> bytes:
    import trimesh

    return trimesh.Trimesh(
        vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], faces=[[0, 1, 2], [1, 3, 2]]
    ).export(file_type="stl")


def test_shapes_preview_and_openapi(server):
    shapes = {s["name"]: s for s in server.get("/api/shapes").json()}
    assert shapes["cube4"]["N"] == 64 and shapes["cube4"]["dimensions"] == [4, 4, 4]
    assert shapes["cube4"]["pieces"]["low"] <= 6 <= shapes["cube4"]["pieces"]["high"]
    r = server.post("/api/shape", data={"resolution": "6"}, files={"file": ("a box.stl", _box_stl())})
    preview = r.json()
    assert r.ok and preview["name"] == "a box.stl" and preview["dimensions"] == [6, 4, 3]
    assert preview["N"] == 72 == len(preview["voxels"]) and preview["pieces"]["max"] == 72
    # The other mesh formats upload as STL does (each format's reading: test_mesh_files.py).
    import trimesh

    for suffix in ("ply", "glb"):
        data = trimesh.creation.box(extents=(3.0, 2.0, 1.5)).export(file_type=suffix)
        r = server.post("/api/shape", data={"resolution": "6"}, files={"file": (f"box.{suffix}", data)})
        assert r.ok and r.json()["dimensions"] == [6, 4, 3], r.text
    # Thin parts: counted for every shape, grown when asked (the same growth as solve --thicken).
    from rllock.core.shapes import load_shape
    from rllock.core.thickness import thicken

    assert shapes["desia-bunny"]["thin"] == 103 and shapes["cube4"]["thin"] == 0
    assert shapes["desia-bunny"]["thin_matters"] and not shapes["cube4"]["thin_matters"]
    grown = server.post("/api/shape", data={"shape": "desia-bunny", "thicken": "3"}).json()
    assert grown["N"] == int(thicken(load_shape("desia-bunny"), 3).sum()) > 966 and grown["thin"] == 0
    r = server.post("/api/shape", data={"shape": "desia-bunny", "thicken": "1"})
    assert r.status_code == 400 and r.json() == {"error": "thicken takes a width of at least 2 voxels, got 1"}
    paths = server.get("/openapi.json").json()["paths"]
    for path in (
        "/api/jobs",
        "/api/jobs/{job_id}",
        "/api/jobs/{job_id}/events",
        "/api/jobs/{job_id}/cancel",
        "/api/jobs/{job_id}/pieces.zip",
        "/api/shape",
        "/api/stats",
    ):
        assert path in paths
    assert "swagger" in server.get("/docs").text.lower()
    page = server.get("/")
    assert page.ok and "/static/app.js" in page.text
    assert server.get("/static/app.js").headers["content-type"].startswith("text/javascript")


def test_a_solve_job_from_request_to_files(server):
    job = server.job(shape="cube4", pieces=6, time_limit=60, seed=1)
    assert job["state"] in ("queued", "running") and job["spec"]["method"] == "solve"
    # Server-sent events until the job ends.
    states = []
    with requests.get(f"{server.url}/api/jobs/{job['id']}/events", stream=True, timeout=120) as stream:
        for line in stream.iter_lines():
            if line.startswith(b"data: "):
                states.append(json.loads(line[6:])["state"])
    done = server.get(f"/api/jobs/{job['id']}").json()
    assert states[-1] == "done" and len(states) >= 2, (states, done.get("error"))
    labels = server.verified(done)
    assert labels.max() == 6
    puz = server.get(done["files"]["assembly.puz"])
    assert "verified valid" in puz.text
    assert server.get(done["files"]["assembly.png"]).content[:8] == b"\x89PNG\r\n\x1a\n"
    r = server.get(done["files"]["pieces.zip"], params={"gap": "0.5", "voxel_size": "5"})
    archive = zipfile.ZipFile(io.BytesIO(r.content))
    stls = sorted(n for n in archive.namelist() if n.endswith(".stl"))
    assert r.ok and len(stls) == 6 and "verified valid" in archive.read("README.txt").decode()
    import trimesh

    key = trimesh.load(io.BytesIO(archive.read(stls[0])), file_type="stl")
    cells = np.argwhere(labels == 1)
    extent = (cells.max(axis=0) - cells.min(axis=0) + 1) * 5.0
    assert key.is_watertight and np.allclose(key.extents, extent - 0.5, atol=1e-6)


def _count(server: ServerProcess) -> int:
    return len(server.get("/api/jobs").json())


BAD = [
    ({"shape": "teapot", "pieces": "5"}, None, 400, "unknown shape"),
    ({"shape": "cube4", "pieces": "65"}, None, 400, "larger than the shape"),
    ({"shape": "cube4", "pieces": "1"}, None, 400, "at least 2"),
    ({"shape": "cube4", "pieces": "six"}, None, 400, "pieces must be a number"),
    ({"shape": "cube4", "method": "generate"}, None, 400, "give the piece count K"),
    ({"shape": "cube4", "pieces": "6", "method": "magic"}, None, 400, "unknown method"),
    ({"shape": "cube4", "pieces": "6", "time_limit": "121"}, None, 400, "at most 120"),
    ({"shape": "cube4", "pieces": "6", "resolution": "8"}, None, 400, "resolution applies only"),
    ({"shape": "cube20", "pieces": "6"}, None, 413, "limit of 5,000"),
    ({"shape": "box:20x2x2", "pieces": "10", "method": "generate"}, None, 400, "no shipped checkpoint"),
    ({"pieces": "6"}, ("x.stl", b"solid nonsense\nfacet normal 0 0\n"), 400, "x.stl"),
    ({"pieces": "6"}, ("flat.stl", None), 400, "flat.stl"),
    ({"pieces": "6"}, ("big.npy", b"\0" * 600_000), 413, "limit of 500,000 bytes"),
    ({"pieces": "6"}, ("huge.npy", b"\0" * 5_000_000), 413, "limit of 500,000 bytes"),
    ({"pieces": "6"}, ("../../etc/passwd", b"x"), 400, "unsupported file 'passwd'"),
]


@pytest.mark.parametrize("fields, upload, status, words", BAD, ids=[b[3] for b in BAD])
def test_bad_input_is_one_line_and_no_job(server, fields, upload, status, words):
    before = _count(server)
    files = None
    if upload is not None:
        name, data = upload
        files = {"file": (name, _flat_stl() if data is None else data)}
    r = server.post("/api/jobs", data=fields, files=files)
    assert r.status_code == status, r.text
    error = r.json()["error"]
    assert list(r.json()) == ["error"] and "\n" not in error and words in error, error
    assert _count(server) == before


def test_bad_ids_and_early_files(server):
    assert server.get("/api/jobs/nonsense").status_code == 404
    assert server.get("/api/jobs/0123456789ab/files/assembly.json").status_code == 404
    job = server.job(shape="mario", pieces=60, time_limit=60)
    try:
        r = server.get(f"/api/jobs/{job['id']}/files/assembly.json")
        assert r.status_code == 409 and "no files" in r.json()["error"]
        assert server.get(f"/api/jobs/{job['id']}/files/secret.txt").status_code == 404
    finally:
        server.post(f"/api/jobs/{job['id']}/cancel")


def test_cancel_and_the_client_limit(server):
    # mario K=60: the solver finds no assembly of seeds 0-6 within 150 s (docs/results.md), so these run
    # until cancelled.
    jobs = [server.job(shape="mario", pieces=60, time_limit=100, seed=s) for s in range(5)]
    r = server.post("/api/jobs", data={"shape": "cube4", "pieces": "6"})
    assert r.status_code == 429 and "limit" in r.json()["error"]
    running = server.wait(jobs[0]["id"], 60, until=("running",))
    assert running["state"] == "running"
    began = time.monotonic()
    for job in jobs:
        assert server.post(f"/api/jobs/{job['id']}/cancel").json()["state"] == "cancelled"
    assert all(server.get(f"/api/jobs/{j['id']}").json()["state"] == "cancelled" for j in jobs)
    assert server.post(f"/api/jobs/{jobs[0]['id']}/cancel").status_code == 409
    # The slots are free again: a new job runs to the end.
    assert server.wait(server.job(shape="cube4", pieces=6)["id"], 60)["state"] == "done"
    assert time.monotonic() - began < 60


def test_concurrent_generate_jobs_share_network_batches(server):
    before = server.get("/api/stats").json()["model"]
    # cube5 K=13: a job makes a few hundred network calls over seconds (cube4's 30 calls in about a second
    # let two jobs miss each other when one worker compiles for longer than the other). Two jobs, the
    # server's two slots: they run at once.
    jobs = [server.job(shape="cube5", pieces=13, method="generate", seed=s, time_limit=100) for s in range(2)]
    done = [server.wait(j["id"], 240) for j in jobs]
    assert [d["state"] for d in done] == ["done"] * 2, [d["error"] for d in done]
    assert all(d["spec"]["checkpoint"] == "cube5-k13" for d in done)
    for d in done:
        assert server.verified(d).max() == 13
    after = server.get("/api/stats").json()["model"]
    calls, merged = after["calls"] - before["calls"], after["requests"] - before["requests"]
    assert calls > 0 and merged / calls > 1.0, after


def test_a_restart_keeps_finished_jobs_and_runs_queued_ones(server):
    finished = [j for j in server.get("/api/jobs").json() if j["state"] == "done"]
    assert finished
    # Two mario K=60 jobs hold both slots (minutes to an assembly, if any), so the ring job is surely still
    # queued when the server stops: alone it can finish before the stop does.
    blockers = [server.job(shape="mario", pieces=60, time_limit=100, seed=s) for s in range(2)]
    pending = server.job(shape="ring", pieces=15, time_limit=60, seed=2)
    for job in blockers:
        server.wait(job["id"], 60, until=("running",))
    assert server.stop() == 0
    on_disk = [server.data / "jobs" / j["id"] / "job.json" for j in (*blockers, pending)]
    states = [json.loads(path.read_text())["state"] for path in on_disk]
    up = server.start()  # before any assertion, so that a failure here leaves the server to the next test
    assert states == ["running", "running", "queued"], states
    assert server.get("/").ok
    jobs = {j["id"]: j for j in server.get("/api/jobs").json()}
    for job in finished:
        assert jobs[job["id"]]["state"] == "done"
        server.verified(jobs[job["id"]])
    assert all(jobs[j["id"]]["state"] in ("queued", "running") for j in blockers)  # run again, not lost
    for job in blockers:
        server.post(f"/api/jobs/{job['id']}/cancel")
    assert server.wait(pending["id"], 90)["state"] == "done"
    assert up < 120


@pytest.mark.skipif(
    not (CHROMIUM.exists() and CHROMEDRIVER.exists()), reason="needs Debian's chromium and chromium-driver"
)
def test_the_web_page_in_headless_chromium(server, tmp_path):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select, WebDriverWait

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in (
        "--headless=new",
        "--no-sandbox",
        "--enable-unsafe-swiftshader",
        "--window-size=1360,1150",
        "--disable-dev-shm-usage",
        f"--user-data-dir={tmp_path / 'profile'}",
    ):
        options.add_argument(flag)
    downloads = tmp_path / "downloads"
    options.add_experimental_option(
        "prefs", {"download.default_directory": str(downloads), "download.prompt_for_download": False}
    )
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    try:
        driver.get(server.url + "/")
        wait = WebDriverWait(driver, 30)
        wait.until(lambda d: d.find_element(By.TAG_NAME, "body").get_attribute("data-phase") == "ready")
        # From the request for the page to its first 3D view of a shape, with the shape list filled.
        # Alone it takes a fraction of a second (lab/first_view.py); the bound is for a loaded test machine
        # beside the rest of the suite, and still catches a page that waits on a solve.
        first_view_ms = driver.execute_script("return window.firstViewMs")
        assert first_view_ms < 3000, first_view_ms
        mesh = tmp_path / "bracket.stl"
        mesh.write_bytes(_box_stl((4.0, 2.0, 2.0)))
        driver.find_element(By.ID, "shape-file").send_keys(str(mesh))
        resolution = driver.find_element(By.ID, "resolution")
        resolution.clear()
        resolution.send_keys("10\t")  # a change event: the preview again, at 10 voxels along the longest side
        wait.until(lambda d: "bracket.stl: N = 250 voxels" in d.find_element(By.ID, "shape-info").text)
        # K left blank: the server picks it, pieces of about 20 voxels where the search finds them quickly.
        assert driver.find_element(By.ID, "pieces").get_attribute("value") == ""
        driver.find_element(By.ID, "start").click()
        WebDriverWait(driver, 120).until(
            lambda d: d.find_element(By.TAG_NAME, "body").get_attribute("data-phase") in ("assembly", "error")
        )
        assert driver.find_element(By.ID, "error").text == ""
        state = driver.find_element(By.ID, "state").text
        assert state.startswith("solve bracket.stl K=12: a valid assembly") and "verified" in state, state
        pieces = 12  # N = 250: pieces of about 20 voxels
        assembled = driver.get_screenshot_as_png()
        assert _colourful(assembled) > 5000
        checkboxes = driver.find_elements(By.CSS_SELECTOR, "#piece-list input[type=checkbox]")
        assert len(checkboxes) == pieces
        driver.execute_script(
            "const s = document.getElementById('slider'); s.value = s.max / 2;"
            "s.dispatchEvent(new Event('input'));"
        )
        assert "comes out" in driver.find_element(By.ID, "step-caption").text
        apart = driver.get_screenshot_as_png()
        assert _changed(assembled, apart) > 2000
        shot = os.environ.get("RLLOCK_SCREENSHOT")
        if shot:
            Path(shot).write_bytes(apart)
        driver.find_element(By.ID, "download-zip").click()
        end = time.monotonic() + 60
        while time.monotonic() < end and not list(downloads.glob("*.zip")):
            time.sleep(0.3)
        archive = zipfile.ZipFile(next(downloads.glob("*.zip")))
        assert len([n for n in archive.namelist() if n.endswith(".stl")]) == pieces
        # A task the search does not finish in its time (mario K=60 in 1 s): the page offers the nearest
        # task that works, found by the server's probe with the same seed, and one click runs it.
        Select(driver.find_element(By.ID, "shape-name")).select_by_value("mario")
        wait.until(lambda d: "mario: N = 548 voxels" in d.find_element(By.ID, "shape-info").text)
        for field, value in (("pieces", "60"), ("time-limit", "1")):
            driver.find_element(By.ID, field).clear()
            driver.find_element(By.ID, field).send_keys(value)
        driver.find_element(By.ID, "start").click()
        offer = driver.find_element(By.ID, "offer")
        WebDriverWait(driver, 120).until(lambda d: offer.is_displayed())
        assert "no valid assembly of mario K=60 within 1 s" in driver.find_element(By.ID, "error").text
        assert offer.text.startswith("Run K=61 (pieces of 8, the last 68): found in "), offer.text
        if shot:
            Path(shot).with_suffix(".failed.png").write_bytes(driver.get_screenshot_as_png())
        offer.click()
        # Until the new job's end: the page stays in its error phase until the click's job starts.
        WebDriverWait(driver, 120).until(
            lambda d: (
                d.find_element(By.ID, "state").text.startswith("solve mario K=61: ")
                and d.find_element(By.TAG_NAME, "body").get_attribute("data-phase") in ("assembly", "error")
            )
        )
        state = driver.find_element(By.ID, "state").text
        assert state.startswith("solve mario K=61: a valid assembly") and "verified" in state, state
        if shot:
            Path(shot).with_suffix(".offer.png").write_bytes(driver.get_screenshot_as_png())
    finally:
        driver.quit()


def _pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def _colourful(png: bytes) -> int:
    rgb = _pixels(png)
    return int(((rgb.max(axis=2) - rgb.min(axis=2)) > 60).sum())


def _changed(a: bytes, b: bytes) -> int:
    return int((np.abs(_pixels(a) - _pixels(b)).sum(axis=2) > 60).sum())
