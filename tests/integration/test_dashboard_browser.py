"""The dashboard in headless Chromium against the real stack (redis-server, API, CPU worker): submit a scene through
the form, watch its progress live, open its page and check that its charts and pictures load; names and errors
holding markup, keys forgotten, refused or of another tenant, and a job deleted while its page is open.

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
from tests.integration.conftest import KEY_A, KEY_B, TINY, client_for, finished, submit, wait_for

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
    from symgs_core.export import save_scene
    from symgs_core.synthetic import synthetic_scene

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


def _not_found_logged(errors: list[str]) -> list[str]:
    """Script errors, less Chromium's notes of a 404: how a page learns that a job is gone or not the key's."""
    return [e for e in errors if "status of 404" not in e]


# Whether the first or last text of an element reads left to right: its first character drawn left of its last.
_READS_LEFT_TO_RIGHT = """(node, last) => {
  const text = last ? node.lastChild : node.firstChild;
  const box = (i) => {
    const range = document.createRange();
    range.setStart(text, i);
    range.setEnd(text, i + 1);
    return range.getBoundingClientRect().x;
  };
  return box(0) < box(text.length - 1);
}"""


def test_names_and_errors_holding_markup_are_shown_as_text(stack, browser: Browser, small_ply: bytes) -> None:  # noqa: ANN001
    # A scene that fails as the worker loads it, with an error that quotes the uploader's file name: markup, a quote
    # (a " would arrive as %22, as browsers send it), and a right-to-left override, which reverses what follows it.
    header, body = small_ply.split(b"end_header\n", 1)
    broken = header + b"end_header\n" + np.float32(np.nan).tobytes() + body[4:]
    hostile = "<img src=x onerror=window.__pwned=1>'\u00e9\u2713\u202e.ply"
    long_name = "scan" * 49 + ".ply"  # 200 characters, the most the API keeps, with nowhere to wrap

    watched = Watched(browser, stack.api_url)
    page = watched.page
    dialogs: list[str] = []
    page.on("dialog", lambda dialog: (dialogs.append(dialog.message), dialog.dismiss()))
    page.goto(f"{stack.api_url}/")
    page.fill("#key-input", KEY_A)
    page.get_by_role("button", name="Use this key").click()
    ids = {}
    link = page.locator("#submit-status a")
    for name in (hostile, long_name):
        page.set_input_files("#scene", {"name": name, "mimeType": "application/octet-stream", "buffer": broken})
        page.get_by_role("button", name="Submit").click()
        link.filter(has_text=name).wait_for(timeout=20_000)
        ids[name] = link.get_attribute("href").rsplit("/", 1)[-1]
        if name == hostile:
            # The override ends with the name: the job's id after it reads as it is.
            assert link.evaluate("a => a.lastChild.textContent") == f" ({ids[hostile][:8]})"
            assert link.evaluate(_READS_LEFT_TO_RIGHT, True)
    assert page.eval_on_selector("#submit-status", "p => p.scrollWidth <= p.clientWidth"), "the name overflows"
    with client_for(stack, KEY_A) as api:
        error = wait_for(api, ids[hostile], finished)["error"]
        assert error["code"] == "non_finite" and hostile in error["message"], error
        wait_for(api, ids[long_name], finished)

    page.get_by_role("button", name="Refresh").click()
    for name, job_id in ids.items():
        page.locator(f'tr[data-job-id="{job_id}"][data-state="failed"]').wait_for(timeout=10_000)
        assert page.locator(f'tr[data-job-id="{job_id}"] a').inner_text() == name
    # However long a name, the row's state and figures stay in view beside it.
    wrap = page.locator(".table-wrap").bounding_box()
    badge = page.locator(f'tr[data-job-id="{ids[long_name]}"] .badge').bounding_box()
    assert badge["x"] + badge["width"] <= wrap["x"] + wrap["width"], (badge, wrap)
    assert page.eval_on_selector(".table-wrap", "w => w.scrollWidth <= w.clientWidth")
    # And in the list, where a narrow window puts the id on the name's line.
    page.set_viewport_size({"width": 400, "height": 900})
    assert page.locator(f'tr[data-job-id="{ids[hostile]}"] .job-id').evaluate(_READS_LEFT_TO_RIGHT, False)
    page.set_viewport_size({"width": 1280, "height": 900})

    page.locator(f'tr[data-job-id="{ids[hostile]}"] a').click()
    page.locator("#error").filter(has_text="non_finite").wait_for(timeout=10_000)
    assert page.locator("#title").inner_text() == hostile and page.title() == f"{hostile} \u00b7 SymGS"
    assert page.locator("#error").inner_text() == f"non_finite: {error['message']}"
    # A job that failed before any mirror level says that none was tried, not that none has started yet.
    assert page.locator("#levels-empty").inner_text() == "No mirror level was tried."
    assert page.locator('img[src="x"]').count() == 0 and page.evaluate("window.__pwned") is None
    assert dialogs == [] and watched.foreign == [] and watched.errors == [], (dialogs, watched.errors)
    watched.context.close()


def use_key_again(page: Page, key: str) -> None:
    """Enter a key through the header's button, and wait for the page that the new key reloads."""
    page.evaluate("window.__beforeKey = true")
    page.get_by_role("button", name="API key: set").click()
    page.fill("#key-input", key)
    page.get_by_role("button", name="Use this key").click()
    page.wait_for_function("() => window.__beforeKey === undefined", timeout=10_000)


def test_the_pages_show_only_what_the_current_key_may_see(stack, browser: Browser, done_job: dict) -> None:  # noqa: ANN001
    watched = Watched(browser, stack.api_url)
    page = watched.page
    with client_for(stack, KEY_A) as api:
        total = api.get("/v1/jobs").json()["total"]
    # An address past the last page (an old link, or its jobs deleted since) shows the last page.
    page.goto(f"{stack.api_url}/?offset=1000")
    page.fill("#key-input", KEY_A)
    page.get_by_role("button", name="Use this key").click()
    last = (total - 1) // 20 * 20
    page.locator("#page-info").filter(has_text=f"{last + 1}\u2013{total} of {total}").wait_for(timeout=10_000)
    assert page.url == f"{stack.api_url}/" + (f"?offset={last}" if last else "")
    page.goto(f"{stack.api_url}/")
    row = page.locator(f'tr[data-job-id="{done_job["id"]}"]')
    row.wait_for(timeout=10_000)

    # Forgetting the key takes its jobs off the screen, as does a key the server refuses.
    page.get_by_role("button", name="Forget key").click()
    page.locator("#key-panel").wait_for(state="visible", timeout=10_000)
    assert page.locator("#jobs tbody tr").count() == 0 and page.locator("#page-info").inner_text() == ""
    # A key with a character no HTTP header can carry is refused by the panel, by name, before any request.
    page.fill("#key-input", "k\u00e9y\u2713")
    page.get_by_role("button", name="Use this key").click()
    assert "not an API key" in page.locator("#key-note").inner_text()
    assert page.locator("#key-toggle").inner_text() == "API key"
    page.fill("#key-input", "not-a-key")
    page.get_by_role("button", name="Use this key").click()
    page.locator("#key-note").filter(has_text="That API key was not accepted.").wait_for(timeout=10_000)
    assert page.locator("#jobs tbody tr").count() == 0

    page.goto(f"{stack.api_url}/jobs/{done_job['id']}")
    page.locator("#key-note").filter(has_text="That API key was not accepted.").wait_for(timeout=10_000)
    page.fill("#key-input", KEY_A)
    page.get_by_role("button", name="Use this key").click()
    page.locator("#metrics-section").wait_for(state="visible", timeout=20_000)
    assert page.locator("#notes").is_hidden() == (not done_job["metrics"]["notes"])
    stages = page.locator("#stages li").count()
    # The same key again: the page starts afresh, with each stage once.
    use_key_again(page, KEY_A)
    page.locator("#metrics-section").wait_for(state="visible", timeout=20_000)
    page.locator("#downloads-section").wait_for(state="visible", timeout=10_000)
    assert page.locator("#stages li").count() == stages
    # Another tenant's key gets nothing of the job, not even what the page showed for the first key.
    use_key_again(page, KEY_B)
    page.locator("#job-status").filter(has_text="There is no job").wait_for(timeout=10_000)
    assert page.locator("#metrics-section").is_hidden() and page.locator("#downloads-section").is_hidden()
    assert page.locator("#title").inner_text() == "Job" and done_job["scene"]["filename"] not in page.title()
    assert watched.foreign == [] and _not_found_logged(watched.errors) == [], watched.errors
    watched.context.close()


def test_job_page_of_a_job_deleted_while_it_is_open(stack, browser: Browser, scene_path: Path) -> None:  # noqa: ANN001
    # A job for a GPU worker stays queued on this stack, which has only a CPU worker.
    with client_for(stack, KEY_A) as api:
        job_id = submit(api, scene_path, {**TINY, "device": "cuda"}).json()["id"]
        watched = Watched(browser, stack.api_url)
        page = watched.page
        page.goto(f"{stack.api_url}/jobs/{job_id}")
        page.fill("#key-input", KEY_A)
        page.get_by_role("button", name="Use this key").click()
        page.locator("#overall-pct").filter(has_text="waiting for a worker").wait_for(timeout=10_000)
        assert api.delete(f"/v1/jobs/{job_id}").status_code == 204
    page.locator("#job-status").filter(has_text="This job was deleted.").wait_for(timeout=20_000)
    assert page.locator("#cancel").is_hidden()
    assert watched.foreign == [] and _not_found_logged(watched.errors) == [], watched.errors
    watched.context.close()


def test_a_jobs_notes_are_shown_above_its_metrics(stack, browser: Browser, tmp_path: Path) -> None:  # noqa: ANN001
    """A scene whose halves are two reconstructions, sent without photographs: its mirror does not pay, and the job
    page says what might make it (a job without notes shows none: see the key test)."""
    from symgs_core.export import save_scene
    from symgs_core.synthetic import synthetic_scene

    scene = tmp_path / "capture.ply"
    save_scene(synthetic_scene("global", n=1500, seed=2, sh_degree=1, capture="independent").scene, scene)
    with client_for(stack, KEY_A) as api:
        response = submit(api, scene, TINY)
        assert response.status_code == 202, response.text
        job = wait_for(api, response.json()["id"], finished, timeout=120)
    assert job["state"] == "succeeded" and len(job["metrics"]["notes"]) == 1, job
    watched = Watched(browser, stack.api_url)
    page = watched.page
    page.goto(f"{stack.api_url}/jobs/{job['id']}")
    page.fill("#key-input", KEY_A)
    page.get_by_role("button", name="Use this key").click()
    notes = page.locator("#notes li")
    notes.first.wait_for(timeout=20_000)
    assert notes.count() == 1 and notes.inner_text() == job["metrics"]["notes"][0]
    assert "--images" in notes.inner_text()
    assert not watched.errors and not watched.foreign


def test_the_api_docs_work_under_the_dashboards_policy(stack, browser: Browser, done_job: dict) -> None:  # noqa: ANN001
    """Swagger UI from the files the service ships, under the dashboard's Content-Security-Policy: it lists every
    operation, and its Authorize box sends the key with a request tried from the page. Nothing else is asked of
    another host, and the policy refuses nothing it needs."""
    watched = Watched(browser, stack.api_url)
    page = watched.page
    page.goto(f"{stack.api_url}/docs")
    page.locator("#operations-operations-healthz_healthz_get").wait_for(timeout=20_000)
    page.locator(".auth-wrapper button.authorize").click()
    page.locator(".modal-ux input").first.fill(KEY_A)
    page.locator(".modal-ux button.authorize").first.click()
    page.locator(".modal-ux button.btn-done").first.click()
    operation = page.locator("#operations-jobs-get_job_v1_jobs__job_id__get")
    operation.locator(".opblock-summary").first.click()
    operation.locator("button.try-out__btn").click()
    operation.locator("input[placeholder='job_id']").fill(done_job["id"])
    operation.locator("button.execute").click()
    body = operation.locator(".live-responses-table .response-col_description pre").first
    body.wait_for(timeout=10_000)
    assert done_job["id"] in body.inner_text() and '"succeeded"' in body.inner_text()
    page.screenshot(path=Path(stack.root) / "docs.png", full_page=False)
    assert watched.foreign == [] and watched.errors == [], (watched.foreign, watched.errors)
    watched.context.close()
