"""The dashboard in headless Chromium against the real stack (redis-server, API, CPU worker): submit a scene through
the form, watch its progress live, open its page and check that its charts and pictures load.

Chromium is Debian's (``apt-get install chromium``), driven by Playwright without any browser download. The tests
that need it skip only when it is not installed or does not start. Screenshots are left in the test's tmp dir."""

from __future__ import annotations

import io
import re
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from PIL import Image
from playwright.sync_api import Browser, Page, sync_playwright
from playwright.sync_api import Error as PlaywrightError

from service.api.errors import install_handlers
from service.dashboard.routes import CSP, MEDIA_TYPES, STATIC, router
from tests.integration.conftest import KEY_A, TINY, client_for

pytestmark = pytest.mark.integration

CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    # WebGL on the CPU (SwiftShader) for the 3D view, which newer Chromium gives only when asked.
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
PAGES = {"index.html", "job.html"}


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        pytest.skip("Chromium is not installed (apt-get install chromium)")
    with sync_playwright() as playwright:
        try:
            chromium = playwright.chromium.launch(executable_path=path, args=CHROMIUM_ARGS)
        except PlaywrightError as exc:
            pytest.skip(f"Chromium did not start: {exc.message.splitlines()[0]}")
        yield chromium
        chromium.close()


class Watched:
    """A page whose requests to other origins are refused and recorded, with its script errors."""

    def __init__(self, browser: Browser, origin: str) -> None:
        self.context = browser.new_context(viewport={"width": 1280, "height": 900}, accept_downloads=True)
        self.foreign: list[str] = []
        self.errors: list[str] = []

        def gate(route, request) -> None:  # noqa: ANN001 - playwright Route, Request
            if request.url.startswith(origin + "/"):
                route.continue_()
            else:
                self.foreign.append(request.url)
                route.abort()

        self.context.route("**/*", gate)
        self.page: Page = self.context.new_page()
        self.page.on("pageerror", lambda exc: self.errors.append(str(exc)))
        self.page.on("console", self._console)

    def _console(self, message) -> None:  # noqa: ANN001 - playwright ConsoleMessage
        # Chromium logs every 4xx; a 401 is how the dashboard learns that the server wants a key. It also
        # sometimes logs an event stream that a script read to its end as cut short (the server ends them
        # cleanly: the service tests read them whole), so network notes about event streams are not errors.
        url = message.location.get("url", "")
        if message.type != "error" or "status of 401" in message.text:
            return
        if message.text.startswith("Failed to load resource: net::") and url.endswith("/events"):
            return
        self.errors.append(f"{message.text} ({url})")


_RECORD_PROGRESS = """() => {
  window.__progress = [];
  window.__left = [];
  const record = (bar) => window.__progress.push([bar.dataset.jobId, bar.hasAttribute("value") ? bar.value : null]);
  new MutationObserver((mutations) => {
    for (const m of mutations) {
      if (m.type === "attributes") record(m.target);
      else if (m.target.classList?.contains("eta")) window.__left.push(m.target.textContent);
      else for (const node of m.addedNodes) node.querySelectorAll?.("progress").forEach(record);
    }
  }).observe(document.querySelector("#jobs tbody"),
             {subtree: true, childList: true, attributes: true, attributeFilter: ["value"]});
  window.__sameDocument = true;
}"""

_IMAGES_LOADED = """(minimum) => {
  const images = [...document.querySelectorAll("figure img")];
  return images.length >= minimum && images.every((img) => img.complete && img.naturalWidth > 0);
}"""
_IMAGES_DECODED = """() => Promise.all([...document.querySelectorAll("figure img")].map((img) => img.decode()))"""


def test_submit_watch_and_inspect_a_job(stack, browser: Browser, scene_path: Path, tmp_path: Path) -> None:  # noqa: ANN001
    watched = Watched(browser, stack.api_url)
    page = watched.page
    page.goto(f"{stack.api_url}/")

    # The server has API keys: the dashboard asks for one before it lists anything.
    page.locator("#key-panel").wait_for(state="visible", timeout=10_000)
    page.fill("#key-input", KEY_A)
    page.get_by_role("button", name="Use this key").click()
    page.locator("#page-info").filter(has_text="of").wait_for(timeout=10_000)

    page.evaluate(_RECORD_PROGRESS)
    page.set_input_files("#scene", scene_path)
    page.select_option("#preset", "small")
    page.select_option("#device", "cpu")
    page.get_by_text("Advanced settings").click()
    for name, value in TINY.items():
        if name != "device":
            page.fill(f"#{name}", str(value))
    page.get_by_role("button", name="Submit").click()

    link = page.locator("#submit-status a")
    link.wait_for(timeout=20_000)
    job_id = link.get_attribute("href").rsplit("/", 1)[-1]
    row = page.locator(f'tr[data-job-id="{job_id}"]')
    row.wait_for(timeout=10_000)
    page.locator(f'tr[data-job-id="{job_id}"][data-state="succeeded"]').wait_for(timeout=90_000)

    assert page.evaluate("window.__sameDocument") is True, "the list reloaded"
    values = [v for jid, v in page.evaluate("window.__progress") if jid == job_id and v is not None]
    assert values == sorted(values), values
    assert values[-1] == 1.0 and len(set(values)) >= 3 and any(0 < v < 1 for v in values), values
    # The time left, as the worker estimates it, counted down between reports; none once the job is done.
    left = page.evaluate("window.__left")
    assert any(re.fullmatch(r"\d+:\d\d left", text) for text in left), left
    assert row.locator(".eta").inner_text() == ""

    with client_for(stack, KEY_A) as api:
        job = api.get(f"/v1/jobs/{job_id}").json()
        report = api.get(f"/v1/jobs/{job_id}/report").json()
        archive = api.get(f"/v1/jobs/{job_id}/result").content
    assert job["params"]["iterations"] == TINY["iterations"] and job["params"]["preset"] == "small"
    assert row.locator("td").nth(5).inner_text() == f"{job['metrics']['ratio_to_ply']:.2f}\u00d7"
    assert row.locator(".pct").inner_text() == "100%"
    page.screenshot(path=tmp_path / "jobs.png", full_page=True)

    page.select_option("#state-filter", "failed")
    page.locator("#jobs-empty").wait_for(state="visible", timeout=10_000)
    assert page.url.endswith("?state=failed") and row.count() == 0
    page.select_option("#state-filter", "succeeded")
    row.wait_for(timeout=10_000)

    row.locator("a").click()
    page.wait_for_url(f"{stack.api_url}/jobs/{job_id}")
    page.locator("#metrics-section").wait_for(state="visible", timeout=10_000)
    page.wait_for_function(_IMAGES_LOADED, arg=4, timeout=30_000)
    sizes = dict(page.eval_on_selector_all("figure img", "els => els.map((e) => [e.dataset.name, e.naturalWidth])"))
    assert {"rate_distortion", "speed_accuracy", "mirrors", "compare_0"} <= set(sizes), sizes
    assert all(width > 0 for width in sizes.values()), sizes
    charts = {a[len("charts/") : -len(".png")] for a in job["artifacts"] if a.startswith("charts/")}
    assert set(sizes) == charts

    metrics = page.locator("#metrics").inner_text()
    assert f"{report['ratio_to_baseline']:.2f}\u00d7" in metrics
    assert len(page.locator("#mirrors tbody tr").all()) == len(report["levels"])
    hrefs = page.eval_on_selector_all("#downloads a", "els => els.map((e) => e.getAttribute('href'))")
    assert {f"/v1/jobs/{job_id}/result", f"/v1/jobs/{job_id}/result.ply", f"/v1/jobs/{job_id}/report"} <= set(hrefs)
    # Downloads go through fetch() with the API key, which a plain link could not send.
    with page.expect_download() as download:
        page.get_by_role("link", name="Compressed archive (.symgs)").click()
    assert Path(download.value.path()).read_bytes() == archive
    assert page.locator("#cancel").is_hidden()
    assert page.locator("#overall-eta").inner_text() == ""
    page.evaluate(_IMAGES_DECODED)
    page.screenshot(path=tmp_path / "job.png", full_page=True)

    assert watched.foreign == [], "the dashboard asked another origin"
    assert watched.errors == [], watched.errors
    watched.context.close()


_LEVEL_MOVING = """() => {
  const bar = document.querySelector('#levels li[data-name="level-0"] progress');
  return bar !== null && bar.hasAttribute("value") && bar.value > 0 && bar.value < 1;
}"""


def test_job_page_cancels_a_running_job(stack, browser: Browser, tmp_path: Path) -> None:  # noqa: ANN001
    from symgs_core.ply import save_scene
    from symgs_core.synthetic import synthetic_scene
    from tests.integration.conftest import submit

    # Near twins, not exact ones: their mirror costs the codec enough to be fine-tuned (exact twins are judged as
    # they start), so the job spends its time in a level whose progress moves.
    scene_path = tmp_path / "near-twins.ply"
    save_scene(synthetic_scene("global", n=2000, seed=3, sh_degree=1, noise=0.001).scene, scene_path)
    slow = {**TINY, "iterations": 2000, "max_levels": 2}
    with client_for(stack, KEY_A) as api:
        job_id = submit(api, scene_path, slow).json()["id"]
    watched = Watched(browser, stack.api_url)
    page = watched.page
    page.goto(f"{stack.api_url}/jobs/{job_id}")
    page.fill("#key-input", KEY_A)
    page.get_by_role("button", name="Use this key").click()
    # Stages, then the level being tuned, appear and move live.
    page.wait_for_function(_LEVEL_MOVING, timeout=60_000)
    assert page.locator("#stages li").count() >= 2 and page.locator("#state").inner_text() == "running"
    page.screenshot(path=tmp_path / "running.png", full_page=True)
    page.get_by_role("button", name="Cancel job").click()
    page.locator("#state").filter(has_text="cancelled").wait_for(timeout=30_000)
    assert page.locator("#cancel").is_hidden()
    page.screenshot(path=tmp_path / "cancelled.png", full_page=True)
    assert watched.foreign == [] and watched.errors == [], (watched.foreign, watched.errors)
    watched.context.close()


def canvas_pixels(page: Page) -> np.ndarray:
    """The 3D view as the page shows it: RGB [H, W, 3] float."""
    with Image.open(io.BytesIO(page.locator("#viewer").screenshot())) as shot:
        return np.asarray(shot.convert("RGB"), dtype=np.float64)


def drawn_share(pixels: np.ndarray) -> float:
    """Share of the pixels that differ from the view's background (its commonest colour)."""
    colours, counts = np.unique(pixels.reshape(-1, 3), axis=0, return_counts=True)
    return float((np.abs(pixels - colours[counts.argmax()]).max(axis=2) > 24).mean())


def wait_for_drawing(page: Page, timeout_s: float = 30.0) -> np.ndarray:
    """The view once splats cover part of it (the depth sort lands a few frames after the scene)."""
    deadline = time.monotonic() + timeout_s
    while True:
        pixels = canvas_pixels(page)
        if drawn_share(pixels) > 0.01 or time.monotonic() > deadline:
            return pixels
        time.sleep(0.5)


def settled(page: Page) -> np.ndarray:
    time.sleep(2.0)  # the view draws for 1.5 s after a change, then rests
    return canvas_pixels(page)


def test_job_page_draws_the_scene_in_3d(stack, browser: Browser, done_job: dict, tmp_path: Path) -> None:  # noqa: ANN001
    watched = Watched(browser, stack.api_url)
    page = watched.page
    page.goto(f"{stack.api_url}/jobs/{done_job['id']}")
    if not page.evaluate("() => Boolean(document.createElement('canvas').getContext('webgl2'))"):
        pytest.skip("this Chromium offers no WebGL 2, not even on the CPU")
    page.fill("#key-input", KEY_A)
    page.get_by_role("button", name="Use this key").click()
    view = page.locator("#viewer")
    page.locator('#viewer[data-state="ready"][data-shown="compressed"]').wait_for(timeout=60_000)
    view.scroll_into_view_if_needed()
    compressed = wait_for_drawing(page)
    assert drawn_share(compressed) > 0.01, "the canvas stayed blank"
    assert "compressed result (.sog)" in page.locator("#viewer-status").inner_text()
    page.screenshot(path=tmp_path / "viewer.png", full_page=True)

    box = view.bounding_box()
    before = settled(page)
    page.mouse.move(box["x"] + box["width"] * 0.5, box["y"] + box["height"] * 0.5)
    page.mouse.down()
    page.mouse.move(box["x"] + box["width"] * 0.8, box["y"] + box["height"] * 0.6, steps=10)
    page.mouse.up()
    dragged = settled(page)
    assert np.abs(dragged - before).mean() > 1.0, "dragging did not turn the view"
    assert drawn_share(dragged) > 0.01

    if done_job["mirrors"]:
        page.get_by_label("Mirror planes").uncheck()
        bare = settled(page)
        assert np.abs(bare - dragged).mean() > 0.05, "the mirror planes were not drawn"
    else:
        assert page.locator("#planes-choice").is_hidden()
        bare = dragged

    # The upload, seen from the same place, looks like the result: both are drawn in the same frame.
    page.get_by_label("Original upload").check()
    page.locator('#viewer[data-state="ready"][data-shown="original"]').wait_for(timeout=60_000)
    wait_for_drawing(page)
    original = settled(page)
    assert drawn_share(original) > 0.01
    assert np.abs(original - bare).mean() < 0.25 * np.abs(dragged - before).mean()
    assert "original upload (.ply)" in page.locator("#viewer-status").inner_text()
    page.get_by_label("Compressed result").check()
    page.locator('#viewer[data-shown="compressed"]').wait_for(timeout=10_000)
    view.screenshot(path=tmp_path / "viewer-canvas.png")

    assert watched.foreign == [], "the 3D view asked another origin"
    assert watched.errors == [], watched.errors
    watched.context.close()


@pytest.fixture(scope="module")
def pages() -> Iterator[TestClient]:
    app = FastAPI()
    install_handlers(app)
    app.include_router(router)
    with TestClient(app) as client:
        yield client


def test_pages_and_files_are_served_with_a_same_origin_policy(pages: TestClient) -> None:
    for path in ("/", "/jobs/3f2c9a1e0b7d4c55a8e6f1d2c3b4a596"):
        response = pages.get(path)
        assert response.status_code == 200 and response.headers["content-type"].startswith("text/html")
        assert response.headers["content-security-policy"] == CSP
    assert "job.js" in pages.get("/jobs/x").text and "jobs.js" in pages.get("/").text
    for name, media_type in MEDIA_TYPES.items():
        response = pages.get(f"/static/{name}")
        assert response.status_code == 200, name
        assert response.headers["content-type"].split(";")[0] == media_type
        assert response.content == (STATIC / name).read_bytes()
    # Every file of the folder is reachable, and nothing else is.
    assert {p.name for p in STATIC.iterdir()} == set(MEDIA_TYPES) | PAGES
    for name in ("routes.py", "..%2Froutes.py", "index.html", ".hidden"):
        assert pages.get(f"/static/{name}").status_code == 404, name
    assert pages.get("/jobs/a..b").status_code == 422


_EXTERNAL = re.compile(
    r"""(?:src|href|action)\s*=\s*["']?\s*(?:[a-z]+:)?//|url\(\s*["']?\s*(?:[a-z]+:)?//|@import|https?://(?!www\.w3\.org/2000/svg")"""
)


def test_no_file_refers_to_another_origin() -> None:
    for path in STATIC.iterdir():
        text = path.read_text()
        assert not _EXTERNAL.search(text), f"{path.name}: {_EXTERNAL.search(text).group(0)!r}"


def test_dashboard_is_part_of_the_running_api(stack) -> None:  # noqa: ANN001
    response = httpx.get(f"{stack.api_url}/", timeout=10)
    assert response.status_code == 200 and "Compression jobs" in response.text
    assert "/" not in httpx.get(f"{stack.api_url}/openapi.json", timeout=10).json()["paths"]
