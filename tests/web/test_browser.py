"""The app and the viewer in a real browser (Chromium by Playwright, WebGL in software), against a real
``panogs serve`` running the real pipeline on a tiny synthetic scene.

One served app, one signed-in page and one finished job are shared by the module's tests, in order: sign in and
upload, reach ``succeeded`` and open the viewer, pixels of the palette, colour modes and the URL, the query against
the API, a refused bundle, another tenant's job, and last, deleting the job.
"""

from __future__ import annotations

import json
import uuid
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from tiny_models import TINY_MAPS
from viewer_page import BACKGROUND, canvas_pixels, look_from_frame

pytestmark = pytest.mark.slow

JOB_TIMEOUT_MS = 300_000  # the tiny scene takes ~15 s alone; the machine may be shared
# Added to the job the upload form creates: the viewer's labels, instances and queries read no stage that reads the
# fit (no checkpoint key includes it), the camera colours are the Gaussians' either way, and the fit has its own
# tests. Its default 120 iterations were a quarter of the job.
SHORT_FIT = {"appearance": {"iterations": 2}}
VIEWPORT = {"width": 1200, "height": 760}
CSP_VIOLATIONS: list[str] = []  # what Chromium refused under the app's Content-Security-Policy, from every page
WHILE_FITTING: dict[str, Any] = {}  # the job's row and its instances while its results are ready and its fit runs
UPLOAD_NOTE: list[str] = []  # what the upload form said under it once the job had succeeded


def _sign_in(context: Any, url: str, key: str) -> Any:
    page = context.new_page()
    page.on("console", lambda m: CSP_VIOLATIONS.append(m.text) if "Content Security Policy" in m.text else None)
    page.goto(f"{url}/app")
    page.fill("#sign-in input[name=key]", key)
    page.click("#sign-in button[type=submit]")
    page.wait_for_selector("#upload")
    return page


@pytest.fixture(scope="module")
def page(browser: Any, served: dict[str, Any]) -> Iterator[Any]:
    context = browser.new_context(viewport=VIEWPORT)
    page = _sign_in(context, served["url"], served["keys"]["alice"])
    yield page
    context.close()


@pytest.fixture(scope="module")
def api(served: dict[str, Any]) -> Iterator[httpx.Client]:
    headers = {"Authorization": f"Bearer {served['keys']['alice']}"}
    with httpx.Client(base_url=served["url"], headers=headers, timeout=30) as client:
        yield client


@pytest.fixture(scope="module")
def job_id(page: Any, bundle_zip: Path, served: dict[str, Any]) -> str:
    """Upload the bundle through the form (tus-js-client), with the connection dropped during the second chunk
    (the client asks the server for its offset and resumes from there), and wait in the job list for
    ``succeeded``. The job the form posts gets ``SHORT_FIT`` on its way to the server."""
    patches: list[str] = []

    def drop_second_chunk(route: Any) -> None:
        if route.request.method == "PATCH":
            patches.append(route.request.url)
            if len(patches) == 2:
                route.abort("connectionreset")
                return
        route.continue_()

    jobs_sent: list[dict[str, Any]] = []

    def short_fit(route: Any) -> None:
        if route.request.method != "POST":
            route.continue_()
            return
        jobs_sent.append(route.request.post_data_json)
        route.continue_(post_data=json.dumps({**jobs_sent[-1], "config": SHORT_FIT}))

    page.route("**/v1/uploads/**", drop_second_chunk)
    page.route("**/v1/jobs", short_fit)
    page.set_input_files("#upload input[type=file]", str(bundle_zip))
    page.click("#upload button[type=submit]")
    row = page.wait_for_selector("#jobs tbody tr[data-job-id]", timeout=120_000)
    page.unroute("**/v1/uploads/**")
    page.unroute("**/v1/jobs")
    assert len(patches) > 2, patches  # the dropped chunk was sent again
    assert [set(body) for body in jobs_sent] == [{"scene_id"}], jobs_sent  # the form's job: no settings of its own
    ident = row.get_attribute("data-job-id")
    try:
        # The results come before the Gaussian fit: the row says so while the job still runs (the tiny room's fit
        # takes some 10-40 s, the table is polled every second).
        fitting = f'tr[data-job-id="{ident}"][data-state=running][data-results=ready]'
        done = f'tr[data-job-id="{ident}"][data-state=succeeded]'
        page.wait_for_selector(f"{fitting}, {done}", timeout=JOB_TIMEOUT_MS)
        if page.locator(fitting).count() == 1:  # else the fit ended between two polls (a fast machine)
            WHILE_FITTING.update(
                fit=page.locator(f"{fitting} td.pgs-fit").inner_text().strip(),
                open=page.locator(f"{fitting} [data-action=open]").count(),
                data_fit=page.locator(fitting).get_attribute("data-fit"),
                instances=httpx.get(
                    f"{served['url']}/v1/jobs/{ident}/instances",
                    headers={"Authorization": f"Bearer {served['keys']['alice']}"},
                ).status_code,
            )
        page.wait_for_selector(f'tr[data-job-id="{ident}"][data-state=succeeded]', timeout=JOB_TIMEOUT_MS)
        UPLOAD_NOTE.append(page.inner_text("#upload-message"))
    except Exception:
        print(served["log"]())
        raise
    return str(ident)


def _open_viewer(page: Any, url: str, job_id: str, view: str = "") -> None:
    # A fresh page load: a new fragment on the same page would keep the open viewer and its state.
    page.goto("about:blank")
    page.goto(f"{url}/app#/jobs/{job_id}{view}")
    page.wait_for_selector(".pgs-viewer[data-state=ready]", timeout=60_000)


def test_the_results_answer_while_the_fit_runs(job_id: str) -> None:
    if not WHILE_FITTING:
        pytest.skip("the fit ended between two polls of the job table: nothing to see while it ran")
    assert WHILE_FITTING["data_fit"] == "running"
    assert WHILE_FITTING["fit"].startswith("fitting "), WHILE_FITTING
    assert WHILE_FITTING["open"] == 1, "the viewer opens on the results"
    assert WHILE_FITTING["instances"] == 200


def test_the_upload_form_does_not_say_job_queued_for_the_whole_run(job_id: str) -> None:
    assert UPLOAD_NOTE == [""], "the job's row says how it goes; the form's note is gone by its end"


def test_upload_reaches_succeeded_and_opens_the_viewer(
    page: Any, job_id: str, served: dict[str, Any], artifacts: Path
) -> None:
    row = page.locator(f'tr[data-job-id="{job_id}"]')
    assert row.locator("td").nth(2).inner_text() == "succeeded"
    assert row.locator("td.pgs-fit").inner_text().strip() == "fitted"
    row.locator("[data-action=open]").click()
    page.wait_for_selector(".pgs-viewer[data-state=ready]", timeout=60_000)
    assert page.locator(".pgs-instances li").count() > 3
    page.screenshot(path=str(artifacts / "viewer.png"))
    scene_id = page.evaluate(f"fetch('/v1/jobs/{job_id}').then(r => r.json()).then(j => j.scene_id)")
    name = page.evaluate(f"fetch('/v1/scenes/{scene_id}').then(r => r.json()).then(s => s.name)")
    page.wait_for_function("name => document.title.startsWith(name)", arg=name)
    assert job_id not in page.title()
    assert page.title() == f"{name} · panogs viewer"
    assert page.inner_text(".pgs-summary").startswith(f"{name}: ")


def test_canvas_draws_the_palette_where_the_scene_is(page: Any, job_id: str, served: dict[str, Any]) -> None:
    _open_viewer(page, served["url"], job_id, "?mode=semantic")
    pixels = canvas_pixels(page).reshape(-1, 3).astype(int)
    header = page.evaluate("window.__panogs.viewer.scene.header")
    shown = [c for c in header["classes"] if c["count"] > 0]
    # Each class's palette colour, drawn exactly (no lighting, no blending), on a share of the canvas.
    present = [c["name"] for c in shown if (np.abs(pixels - c["color"]).sum(axis=1) == 0).mean() > 0.001]
    assert len(present) >= 3, f"palette colours on the canvas: {present}"
    background = (np.abs(pixels - BACKGROUND).sum(axis=1) <= 3).mean()
    assert 0.05 < background < 0.95  # the scene covers part of the canvas, not none and not all


def test_the_fitted_scene_draws_points_no_larger_than_their_spacing(
    page: Any, job_id: str, served: dict[str, Any]
) -> None:
    # The fit grows Gaussians up to 4x their start to close gaps softly; drawn as hard opaque discs at that size
    # the tiny room's first view was big overlapping discs. The points keep the radius the fit started from.
    from panogs_core.stages.primitives import gaussian_log_scales

    _open_viewer(page, served["url"], job_id)
    position, scale = page.evaluate("(v => [Array.from(v.scene.position), Array.from(v.scene.scale)])"
                                    "(window.__panogs.viewer)")  # fmt: skip
    spacing = np.exp(gaussian_log_scales(np.asarray(position, np.float32).reshape(-1, 3))[:, 0])
    assert (np.asarray(scale) <= spacing * 1.0001).all()
    assert np.median(scale) > 0.5 * np.median(spacing)  # still the fitted size where it is smaller


def test_colour_modes_change_the_pixels_and_the_url_reopens_the_view(
    page: Any, job_id: str, served: dict[str, Any], artifacts: Path
) -> None:
    _open_viewer(page, served["url"], job_id, "?mode=semantic")
    semantic = canvas_pixels(page)
    page.keyboard.press("1")
    camera = canvas_pixels(page, artifacts / "camera.png")
    page.keyboard.press("3")
    instance = canvas_pixels(page, artifacts / "instance.png")
    for a, b in ((semantic, camera), (semantic, instance), (camera, instance)):
        assert (np.abs(a.astype(int) - b).sum(axis=2) > 30).mean() > 0.02
    assert "mode=instance" in page.url
    page.reload()
    page.wait_for_selector(".pgs-viewer[data-state=ready]", timeout=60_000)
    assert page.get_attribute(".pgs-viewer", "data-mode") == "instance"
    page.keyboard.press("?")
    assert page.locator(".pgs-help").is_visible()


def _look_from_key_frame(page: Any, api: httpx.Client, job_id: str) -> str:
    """Put the viewer's camera at the first key frame's pose and field of view (cameras.json); its frame id."""
    cameras = api.get(f"/v1/jobs/{job_id}/artifacts/cameras.json").json()
    look_from_frame(page, cameras["frames"][0], cameras["camera"])
    return str(cameras["frames"][0]["id"])


def test_photo_mode_draws_the_fitted_splats_with_the_labels_over_them(
    page: Any, job_id: str, served: dict[str, Any], api: httpx.Client, synth_tiny: Path, artifacts: Path
) -> None:
    _open_viewer(page, served["url"], job_id, "?mode=camera")
    assert page.get_attribute(".pgs-viewer", "data-photo") == "off"
    frame_id = _look_from_key_frame(page, api, job_id)
    page.wait_for_timeout(300)
    points = canvas_pixels(page)
    page.keyboard.press("p")
    page.wait_for_selector(".pgs-viewer[data-photo=on]", timeout=120_000)
    page.wait_for_timeout(1500)  # the splats' depth order comes from Spark's worker a few frames later
    photo = canvas_pixels(page, artifacts / "photo.png")
    background = BACKGROUND
    covered = (np.abs(photo.astype(int) - background).sum(axis=2) > 12).mean()
    assert covered > 0.3, f"the splats cover {covered:.0%} of the canvas"
    assert (np.abs(photo.astype(int) - points).sum(axis=2) > 30).mean() > 0.05, "the photo is not the points"
    page.keyboard.press("2")  # the class colours over the photo
    page.wait_for_timeout(500)
    over = canvas_pixels(page, artifacts / "photo-semantic.png")
    assert (np.abs(over.astype(int) - photo).sum(axis=2) > 30).mean() > 0.05
    assert page.get_attribute(".pgs-viewer", "data-photo") == "on"
    # The photo beside the key frame's colour image, seen from the same pose (the canvas's aspect differs).
    folder = synth_tiny  # the bundle the job's zip was made from
    scene = json.loads((folder / "scene.json").read_text())
    color_path = next(f["color"] for f in scene["frames"] if f["id"] == frame_id)
    colour = cv2.imread(str(folder / color_path))
    height = photo.shape[0]
    colour = cv2.resize(colour, (round(colour.shape[1] * height / colour.shape[0]), height))
    cv2.imwrite(str(artifacts / "photo-beside-colour-frame.png"), np.hstack([photo[:, :, ::-1], colour]))
    page.keyboard.press("p")
    page.wait_for_selector(".pgs-viewer[data-photo=off]")


def test_look_from_a_capture_frame_puts_the_camera_at_its_pose_and_the_url_keeps_it(
    page: Any, job_id: str, served: dict[str, Any], api: httpx.Client, artifacts: Path
) -> None:
    cameras = api.get(f"/v1/jobs/{job_id}/artifacts/cameras.json").json()
    frame = cameras["frames"][len(cameras["frames"]) // 2]
    _open_viewer(page, served["url"], job_id, "?mode=camera")
    choose = page.locator("[data-role=frame]")
    choose.wait_for(state="visible")
    ids = choose.locator("option").evaluate_all("els => els.map(e => e.value)")
    assert ids == ["", *(str(f["id"]) for f in cameras["frames"])]
    read = "(c => [c.position.toArray(), c.up.toArray(), c.fov])(window.__panogs.viewer.camera)"
    choose.select_option(str(frame["id"]))
    pose = np.asarray(frame["T_world_cam"])
    fov = np.degrees(2 * np.arctan(cameras["camera"]["height"] / (2 * cameras["camera"]["fy"])))

    def at_the_frame() -> None:
        position, up, shown_fov = page.evaluate(read)
        np.testing.assert_allclose(position, pose[:3, 3], atol=1e-5)
        np.testing.assert_allclose(up, -pose[:3, 1], atol=1e-5)  # the frame's own up: OpenCV's y points down
        assert shown_fov == pytest.approx(fov)

    at_the_frame()
    assert f"frame={frame['id']}" in page.url
    canvas_pixels(page, artifacts / "look-from-frame.png")
    page.reload()  # the URL keeps the frame's view, roll and field of view included
    page.wait_for_selector(".pgs-viewer[data-state=ready]", timeout=60_000)
    page.wait_for_function("() => window.__panogs.viewer.cameras !== null")
    at_the_frame()
    page.keyboard.press("f")  # the orbit view again: z up, the frame forgotten
    assert page.evaluate(read)[1] == [0, 0, 1]
    assert "frame=" not in page.url


def _fit_running_for(page: Any, job_id: str, polls: int) -> list[int]:
    """The job answers "results ready, fit running" to the page's next ``polls`` status requests, then as it is
    (succeeded, fitted): a viewer opened while the fit ran. Returns the list the answers are counted in."""
    seen: list[int] = []

    def running(route: Any) -> None:
        if route.request.method != "GET" or len(seen) >= polls:
            route.continue_()
            return
        seen.append(1)
        job = route.fetch().json()
        job.update(state="running", results_ready=True, fit={**(job.get("fit") or {}), "state": "running",
                   "progress": 0.4})  # fmt: skip
        route.fulfill(json=job)

    page.route(f"**/v1/jobs/{job_id}", running)
    return seen


def test_a_viewer_opened_while_the_fit_runs_offers_the_photo_when_it_ends(
    page: Any, job_id: str, served: dict[str, Any], artifacts: Path
) -> None:
    seen = _fit_running_for(page, job_id, polls=3)  # the check on opening, then two of the viewer's polls
    try:
        _open_viewer(page, served["url"], job_id, "?mode=semantic")
        assert page.get_attribute(".pgs-viewer", "data-photo") == "unavailable"
        assert "being fitted (40%)" in page.inner_text(".pgs-fit-note")
        page.keyboard.press("p")  # nothing to show yet
        assert page.get_attribute(".pgs-viewer", "data-photo") == "unavailable"
        # The fit ends (the job's own status from the fourth request on): offered without a reload.
        page.wait_for_selector(".pgs-viewer[data-photo=off]", timeout=20_000)
        assert len(seen) == 3
        assert page.locator(".pgs-fit-note").count() == 0
        assert page.locator("[data-action=photo]").is_visible()
    finally:
        page.unroute(f"**/v1/jobs/{job_id}")

    def slow_ply(route: Any) -> None:  # long enough to see what the canvas says while the splats load
        page.wait_for_timeout(1500)
        route.continue_()

    page.route("**/artifacts/gaussians.ply", slow_ply)
    try:
        page.keyboard.press("p")
        page.wait_for_selector(".pgs-photo-loading:visible", timeout=5_000)
        assert "loading" in page.inner_text(".pgs-photo-loading")
        page.screenshot(path=str(artifacts / "photo-loading.png"))
        page.wait_for_selector(".pgs-viewer[data-photo=on]", timeout=120_000)
        assert not page.locator(".pgs-photo-loading").is_visible()
    finally:
        page.unroute("**/artifacts/gaussians.ply")
    assert "photo=1" in page.url
    page.reload()  # the URL keeps the photo view
    page.wait_for_selector(".pgs-viewer[data-photo=on]", timeout=120_000)


def test_a_query_lists_its_best_candidates_below_the_threshold_and_the_threshold_lowers(
    page: Any, job_id: str, served: dict[str, Any], api: httpx.Client, artifacts: Path
) -> None:
    _open_viewer(page, served["url"], job_id)
    instances = api.get(f"/v1/jobs/{job_id}/instances").json()["data"]
    name = next(i["class_name"] for i in instances if i["kind"] == "thing")
    answer = api.post(f"/v1/jobs/{job_id}/query", json={"text": name}).json()
    assert answer["candidates"]
    assert all(c["score"] < 0.5 for c in answer["candidates"])
    page.fill(".pgs-query input", name)
    page.press(".pgs-query input", "Enter")
    page.wait_for_selector(".pgs-viewer[data-query=done]")
    read = "els => els.map(e => +(e.dataset.hitId ?? e.dataset.candidateId))"
    assert page.locator("[data-hit-id]").evaluate_all(read) == [h["instance_id"] for h in answer["hits"]]
    below = page.locator("[data-candidate-id]")
    assert below.evaluate_all(read) == [c["instance_id"] for c in answer["candidates"]]
    assert all("below" in text for text in below.all_inner_texts())
    lit = {int(x) for x in page.get_attribute(".pgs-viewer", "data-lit").split(",")}
    assert lit == {h["instance_id"] for h in answer["hits"]}, "a candidate is listed, not lit"
    page.screenshot(path=str(artifacts / "query-candidates.png"))
    # The threshold lowered in place: the query is asked again and what now passes is lit.
    lowered = api.post(f"/v1/jobs/{job_id}/query", json={"text": name, "min_score": 0.0}).json()
    assert len(lowered["hits"]) > len(answer["hits"])
    page.fill("[data-role=threshold]", "0")
    page.press("[data-role=threshold]", "Enter")
    page.wait_for_function("n => document.querySelectorAll('[data-hit-id]').length === n", arg=len(lowered["hits"]))
    assert page.locator("[data-hit-id]").evaluate_all(read) == [h["instance_id"] for h in lowered["hits"]]
    assert "min=0&" in page.url or page.url.endswith("min=0")
    # Free text at the default threshold: ranked instances with their scores, passing or the closest below it.
    page.fill("[data-role=threshold]", "0.5")
    page.press("[data-role=threshold]", "Enter")
    page.wait_for_function("() => document.querySelector('.pgs-query-status').textContent.includes('≥ 0.50')")
    text = "something soft to sit on"
    page.fill(".pgs-query input", text)
    page.press(".pgs-query input", "Enter")
    page.wait_for_selector(".pgs-viewer[data-query=done]", timeout=120_000)  # the encoder's first start
    free = api.post(f"/v1/jobs/{job_id}/query", json={"text": text}).json()
    assert free["query_kind"] == "text"
    listed = page.locator("[data-hit-id], [data-candidate-id]").evaluate_all(read)
    assert listed == [h["instance_id"] for h in free["hits"] + free["candidates"]]
    assert listed, "a free-text question always gets ranked instances"
    _assert_scores_shown(page, free["hits"] + free["candidates"])
    page.screenshot(path=str(artifacts / "query-free-text.png"))
    page.keyboard.press("Escape")


def _assert_scores_shown(page: Any, ranked: list[dict[str, Any]]) -> None:
    """The answer list shows each score in three decimals, or in its first two digits where those read 0.000."""
    shown = [float(x) for x in page.locator(".pgs-hits .pgs-score").all_inner_texts()]
    assert len(shown) == len(ranked)
    for text, answer in zip(shown, ranked, strict=True):
        score = answer["score"]
        assert text == (pytest.approx(score, rel=0.06) if 0 < abs(score) < 5e-4 else round(score, 3)), (text, score)


def test_class_query_lights_exactly_the_instances_the_api_returns(
    page: Any, job_id: str, served: dict[str, Any], api: httpx.Client
) -> None:
    _open_viewer(page, served["url"], job_id)
    instances = api.get(f"/v1/jobs/{job_id}/instances").json()["data"]
    name = next(i["class_name"] for i in instances if i["kind"] == "thing")
    expected = [h["instance_id"] for h in api.post(f"/v1/jobs/{job_id}/query", json={"text": name}).json()["hits"]]
    assert expected
    page.fill(".pgs-query input", name)
    page.press(".pgs-query input", "Enter")
    page.wait_for_selector(".pgs-viewer[data-query=done]")
    listed = [int(x) for x in page.locator("[data-hit-id]").evaluate_all("els => els.map(e => e.dataset.hitId)")]
    assert listed == expected  # same instances, same order
    lit = page.get_attribute(".pgs-viewer", "data-lit")
    assert sorted(int(x) for x in lit.split(",")) == sorted(expected)


def test_clicking_a_point_selects_its_instance(page: Any, job_id: str, served: dict[str, Any]) -> None:
    _open_viewer(page, served["url"], job_id)
    # Every class but that of the largest thing instance hidden (hidden points cannot be picked), then the screen
    # position of one of its primitives, projected by the viewer's own camera.
    x, y, expected_class = page.evaluate(
        """() => {
          const v = window.__panogs.viewer;
          const things = v.scene.header.instances.filter(i => i.kind === "thing");
          const big = things.reduce((a, b) => (b.num_points > a.num_points ? b : a));
          for (const c of v.scene.header.classes) if (c.index !== big.class_index) v.toggleClass(c.index, false);
          const i = v.scene.instance.findIndex(id => id === big.id);
          const p = v.scene.position;
          const ndc = new v.camera.position.constructor(p[3 * i], p[3 * i + 1], p[3 * i + 2]).project(v.camera);
          const r = v.renderer.domElement.getBoundingClientRect();
          return [r.left + (ndc.x + 1) / 2 * r.width, r.top + (1 - ndc.y) / 2 * r.height, big.class_name];
        }"""
    )
    page.mouse.click(x, y)
    lit = page.get_attribute(".pgs-viewer", "data-lit")
    assert lit, "a click on the scene selected nothing"
    selected = int(lit)
    assert page.locator(f'.pgs-instances li[data-instance-id="{selected}"].pgs-lit').count() == 1
    assert f"sel={selected}" in page.url
    picked = page.evaluate(f"window.__panogs.viewer.instanceById.get({selected}).class_name")
    assert picked == expected_class
    assert page.evaluate("window.__panogs.viewer.boxes.length") == 1  # its box is drawn


def test_refused_bundle_shows_its_problems_one_per_line(
    page: Any, served: dict[str, Any], api: httpx.Client, tmp_path: Path
) -> None:
    broken = tmp_path / "broken.zip"
    with zipfile.ZipFile(broken, "w") as zf:
        zf.writestr("scene.json", '{"format_version": 1, "name": "broken"}')
        zf.writestr("frames/readme.txt", "no frames here")
    page.goto(f"{served['url']}/app#/")
    page.set_input_files("#upload input[type=file]", str(broken))
    page.click("#upload button[type=submit]")
    page.wait_for_selector("#upload-message .pgs-problems li", timeout=60_000)
    shown = page.locator("#upload-message .pgs-problems li").all_inner_texts()
    # The API's own answer for the same archive: the same problems, in the same order.
    data = broken.read_bytes()
    created = api.post("/v1/uploads", content=data, headers={"Tus-Resumable": "1.0.0", "Upload-Length": str(len(data)),
                       "Content-Type": "application/offset+octet-stream"})  # fmt: skip
    refused = api.post("/v1/scenes", json={"upload_id": created.json()["id"]})
    assert refused.status_code == 422
    assert shown == refused.json()["problems"]
    assert len(shown) >= 2


def test_another_tenants_job_cannot_be_opened(browser: Any, job_id: str, served: dict[str, Any]) -> None:
    context = browser.new_context(viewport=VIEWPORT)
    try:
        other = _sign_in(context, served["url"], served["keys"]["mallory"])
        other.goto(f"{served['url']}/app#/jobs/{job_id}")
        other.wait_for_selector(".pgs-message.pgs-bad")
        assert f"job {job_id} not found" in other.inner_text("#page")
        assert other.locator("canvas").count() == 0
        assert job_id not in other.inner_text("#jobs") if other.locator("#jobs").count() else True
    finally:
        context.close()


def test_an_open_rerun_form_keeps_its_text_and_focus_while_the_table_polls(
    page: Any, job_id: str, served: dict[str, Any]
) -> None:
    page.goto("about:blank")
    page.goto(f"{served['url']}/app#/")
    row = page.locator(f'tr[data-job-id="{job_id}"]')
    row.locator("[data-action=re-run]").click()
    settings = row.locator("[data-field='clustering.thresholds']")
    settings.fill("0.8, 0.7")
    for _ in range(2):  # two polls of the table: each used to move every row, which takes the focus away
        with page.expect_response(lambda r: "/v1/jobs?limit=" in r.url, timeout=15_000):
            pass
        page.wait_for_timeout(100)  # the answer is drawn
    assert settings.evaluate("el => el === document.activeElement")
    page.keyboard.type(" ")  # typing goes on where it was
    assert settings.input_value() == "0.8, 0.7 "
    row.locator("[data-action=re-run]").click()  # the next test opens its own form


def test_rerun_form_checks_as_typed_and_keeps_what_was_typed_on_a_refusal(
    page: Any, job_id: str, served: dict[str, Any], artifacts: Path
) -> None:
    page.goto(f"{served['url']}/app#/")
    row = page.locator(f'tr[data-job-id="{job_id}"]')
    row.locator("[data-action=re-run]").click()
    form = row.locator("form.pgs-rerun")
    thresholds = form.locator("[data-field='clustering.thresholds']")
    thresholds.fill("0.7, 0.9")  # increasing: refused as typed
    assert thresholds.get_attribute("aria-invalid") == "true"
    assert "larger than 0.7" in form.locator(".pgs-field-note").first.inner_text()
    assert form.locator("[data-field=fit]").is_checked()
    assert not form.locator("textarea").is_visible(), "the raw JSON is the advanced option, folded"
    before = page.evaluate("fetch('/v1/jobs').then(r => r.json()).then(b => b.count)")
    form.locator("button[type=submit]").click()
    assert "larger than 0.7" in form.locator("[data-role=form-error]").inner_text()
    thresholds.fill("0.9, 0.7")
    assert thresholds.get_attribute("aria-invalid") == "false"
    form.locator("summary").click()
    advanced = form.locator("textarea")
    assert json.loads(advanced.input_value()) == SHORT_FIT  # the job's other settings, kept for the re-run
    advanced.fill('{"clustering": {"bogus": 1}')  # not JSON
    form.locator("button[type=submit]").click()
    assert "not valid JSON" in form.locator("[data-role=form-error]").inner_text()
    advanced.fill('{"clustering": {"bogus": 1}}')  # JSON, refused by the server: an unknown key
    form.locator("button[type=submit]").click()
    page.wait_for_function("() => /bogus/.test(document.querySelector('[data-role=form-error]').textContent)")
    assert advanced.input_value() == '{"clustering": {"bogus": 1}}'
    assert thresholds.input_value() == "0.9, 0.7"
    assert page.evaluate("fetch('/v1/jobs').then(r => r.json()).then(b => b.count)") == before
    box = form.bounding_box()
    card = page.locator("#jobs").bounding_box()
    assert box is not None
    assert card is not None
    assert box["x"] + box["width"] <= card["x"] + card["width"] + 1
    page.screenshot(path=str(artifacts / "rerun-form.png"))
    row.locator("[data-action=re-run]").click()  # the next test opens its own form


def test_rerun_with_other_settings_then_cancel(
    page: Any, job_id: str, served: dict[str, Any], api: httpx.Client
) -> None:
    page.goto(f"{served['url']}/app#/")
    row = page.locator(f'tr[data-job-id="{job_id}"]')
    row.locator("[data-action=re-run]").click()
    row.locator("[data-field='clustering.thresholds']").fill("0.9, 0.7")
    row.locator("[data-field=fit]").uncheck()
    row.locator("input[aria-label=vocabulary]").fill("lamp, rug, wall")  # an inline vocabulary, by names
    before = {j["id"] for j in api.get("/v1/jobs").json()["data"]}
    row.locator("form button[type=submit]").click()
    # The new job's row: the first id the table did not list before (another test's job may be running too).
    known = ",".join(f'[data-job-id="{j}"]' for j in before)
    new = page.wait_for_selector(f"#jobs tbody tr[data-job-id]:not({known})")
    new_id = new.get_attribute("data-job-id")
    assert new_id not in before
    # The form closed with a confirmation that names the new job.
    assert row.locator("form").count() == 0
    assert f"re-run queued as job {new_id[:8]}" in row.locator("[data-role=message]").inner_text()
    created = api.get(f"/v1/jobs/{new_id}").json()
    assert created["config"] == {"appearance": {**SHORT_FIT["appearance"], "enabled": False},
                                 "clustering": {"thresholds": [0.9, 0.7]}}  # fmt: skip
    kinds = {"lamp": "thing", "rug": "thing", "wall": "stuff"}
    assert created["vocabulary"] == {"classes": [{"name": n, "kind": k} for n, k in kinds.items()]}
    page.locator(f'tr[data-job-id="{new_id}"] [data-action=cancel]').click()
    page.wait_for_selector(f'tr[data-job-id="{new_id}"][data-state=canceled]', timeout=60_000)


def test_a_rerun_with_other_clustering_settings_shows_the_stages_it_reused(
    page: Any, job_id: str, served: dict[str, Any], api: httpx.Client
) -> None:
    page.goto(f"{served['url']}/app#/")
    row = page.locator(f'tr[data-job-id="{job_id}"]')
    first = api.get(f"/v1/jobs/{job_id}").json()
    row.locator("[data-action=re-run]").click()
    assert first["config"] == SHORT_FIT  # kept by the form's advanced settings; the vocabulary field as it was
    row.locator("[data-field='clustering.thresholds']").fill("0.9, 0.75, 0.6")
    before = {j["id"] for j in api.get("/v1/jobs").json()["data"]}
    row.locator("form button[type=submit]").click()
    known = ",".join(f'[data-job-id="{j}"]' for j in before)
    new_id = page.wait_for_selector(f"#jobs tbody tr[data-job-id]:not({known})").get_attribute("data-job-id")
    done = page.wait_for_selector(f'tr[data-job-id="{new_id}"][data-state=succeeded]', timeout=JOB_TIMEOUT_MS)
    reused = set((done.get_attribute("data-cached") or "").split())
    assert {"primitives", "fusion", "language_field"} <= reused  # taken from the first job's checkpoints
    assert "clustering" not in reused  # its settings changed: computed again
    assert "reused: " in done.inner_text()
    shown = api.get(f"/v1/jobs/{new_id}").json()["stage_cached"]
    assert reused == {stage for stage, cached in shown.items() if cached}


def test_a_tiled_job_shows_each_tile_and_the_merge_in_its_row(
    page: Any, job_id: str, served: dict[str, Any], api: httpx.Client
) -> None:
    scene_id = api.get(f"/v1/jobs/{job_id}").json()["scene_id"]
    created = api.post("/v1/jobs", json={"scene_id": scene_id, "tiling": {"tiles": "2x1"}})
    assert created.status_code == 202, created.text
    tiled = created.json()["id"]
    page.goto("about:blank")
    page.goto(f"{served['url']}/app#/")
    row = f'tr[data-job-id="{tiled}"]'
    page.wait_for_selector(f"{row} li[data-tile]", timeout=JOB_TIMEOUT_MS)  # the plan is made: one line a tile
    page.wait_for_selector(f"{row}[data-state=succeeded]", timeout=JOB_TIMEOUT_MS)
    lines = page.locator(f"{row} li[data-tile]")
    shown = {lines.nth(i).get_attribute("data-tile"): lines.nth(i).get_attribute("data-tile-state")
             for i in range(lines.count())}  # fmt: skip
    assert shown == {"tile 1": "succeeded", "tile 2": "succeeded", "merge": "succeeded"}
    status = api.get(f"/v1/jobs/{tiled}").json()
    assert [t["kind"] for t in status["tiles"]].count("tile") == 2
    assert page.locator(f"{row} [data-action=open]").count() == 1  # the merged result opens in the viewer


def test_deleting_the_job_removes_it_and_its_files(
    page: Any, job_id: str, served: dict[str, Any], api: httpx.Client
) -> None:
    folder = served["storage"] / "artifacts" / str(uuid.UUID(job_id))
    assert (folder / "gaussians.ply").is_file()
    page.goto(f"{served['url']}/app#/")
    row = page.wait_for_selector(f'tr[data-job-id="{job_id}"]')
    page.once("dialog", lambda dialog: dialog.accept())
    row.query_selector("[data-action=delete]").click()
    page.wait_for_selector(f'tr[data-job-id="{job_id}"]', state="detached", timeout=15_000)
    assert not folder.exists()
    assert api.get(f"/v1/jobs/{job_id}").status_code == 404
    # Its viewer's URL says so and leads back to the jobs.
    page.goto("about:blank")
    page.goto(f"{served['url']}/app#/jobs/{job_id}")
    page.wait_for_selector(".pgs-message.pgs-bad [data-action=back]")
    page.click("[data-action=back]")
    page.wait_for_selector("#upload")


# The tiny random models' settings (tiny_models.TINY_MAPS: every mask kept, small grids); a short fit.
MAPS_RUN = {"maps2d": TINY_MAPS, "language_field": {"epochs": 1, "min_steps": 1}, "appearance": {"iterations": 20}}


def test_a_capture_without_maps_runs_on_the_chosen_models_and_answers_free_text(
    page: Any, served: dict[str, Any], bare_bundle_zip: Path, api: httpx.Client, artifacts: Path
) -> None:
    """A new user's capture, posed colour and depth alone: the upload form offers the operator's 2D models, the job
    names them, the viewer opens from the job's row as soon as the results are ready and offers the photo view when
    the fit ends (no reload), and a free-text question, embedded by the chosen CLIP's text tower, gets ranked
    instances with their scores. Random weights: the order means nothing; the path is what is checked."""
    if not served["map_models"]:
        pytest.skip("no 2D models to offer: transformers is not installed")
    page.goto(f"{served['url']}/app#/")
    page.wait_for_selector(".pgs-map-models:not([hidden])")
    values = "els => els.map(e => e.value)"
    assert page.locator("select[name=masks-model] option").evaluate_all(values) == ["tiny-sam"]
    assert page.locator("select[name=features-model] option").evaluate_all(values) == ["tiny-clip"]
    sent: list[dict[str, Any]] = []

    def with_settings(route: Any) -> None:
        if route.request.method != "POST":
            route.continue_()
            return
        sent.append(route.request.post_data_json)
        route.continue_(post_data=json.dumps({**sent[-1], "config": MAPS_RUN}))

    page.route("**/v1/jobs", with_settings)
    try:
        page.set_input_files("#upload input[type=file]", str(bare_bundle_zip))
        page.click("#upload button[type=submit]")
        page.wait_for_function("() => document.querySelector('#upload-message').textContent.includes('job queued')")
    finally:
        page.unroute("**/v1/jobs")
    assert [set(body) for body in sent] == [{"scene_id", "maps"}], sent
    assert sent[0]["maps"] == {"masks": "tiny-sam", "features": "tiny-clip"}
    scene = api.get(f"/v1/scenes/{sent[0]['scene_id']}").json()
    assert (scene["has_mask_maps"], scene["has_feature_maps"]) == (False, False)
    (job,) = api.get("/v1/jobs", params={"scene_id": scene["id"]}).json()["data"]
    ready = f'tr[data-job-id="{job["id"]}"][data-results=ready]'
    try:
        page.wait_for_selector(ready, timeout=JOB_TIMEOUT_MS)
    except Exception:
        print(served["log"]())
        raise
    page.evaluate("window.__sameDocument = true")  # gone if anything below reloads the page
    page.click(f"{ready} [data-action=open]")
    page.wait_for_selector(".pgs-viewer[data-state=ready]", timeout=60_000)
    opened_while_fitting = page.get_attribute(".pgs-viewer", "data-photo") == "unavailable"
    text = "a wooden cabinet"
    page.fill(".pgs-query input", text)
    page.press(".pgs-query input", "Enter")
    page.wait_for_selector(".pgs-viewer[data-query=done]", timeout=120_000)  # the CLIP text tower's first load
    free = api.post(f"/v1/jobs/{job['id']}/query", json={"text": text}).json()
    assert free["query_kind"] == "text"
    ranked = free["hits"] + free["candidates"]
    read = "els => els.map(e => +(e.dataset.hitId ?? e.dataset.candidateId))"
    listed = page.locator("[data-hit-id], [data-candidate-id]").evaluate_all(read)
    assert listed == [h["instance_id"] for h in ranked]
    assert listed, "a free-text question always gets ranked instances"
    _assert_scores_shown(page, ranked)
    page.wait_for_selector(".pgs-viewer[data-photo=off]", timeout=JOB_TIMEOUT_MS)  # offered when the fit ends
    assert page.evaluate("window.__sameDocument") is True, "the photo view came without a reload"
    assert page.locator("[data-action=photo]").is_visible()
    page.screenshot(path=str(artifacts / "capture-without-maps.png"))
    report = api.get(f"/v1/jobs/{job['id']}/artifacts/report.json").json()
    assert report["feature_space"].startswith("clip-vit-"), "the features are the chosen CLIP's"
    assert api.get(f"/v1/jobs/{job['id']}").json()["stage_cached"]["maps_2d"] is False
    print(f"viewer opened while the fit ran: {opened_while_fitting}")
    # Its re-run names the same models (the scene still has no maps of its own); deleted at once, as the re-run
    # tests above cover the run itself.
    page.goto(f"{served['url']}/app#/")
    row = page.locator(f'tr[data-job-id="{job["id"]}"]')
    rerun: list[dict[str, Any]] = []

    def record(route: Any) -> None:
        if route.request.method == "POST":
            rerun.append(route.request.post_data_json)
        route.continue_()

    page.route("**/v1/jobs", record)
    try:
        row.locator("[data-action=re-run]").click()
        row.locator("[data-field=fit]").uncheck()
        row.locator("form button[type=submit]").click()
        row.locator("[data-role=message]", has_text="re-run queued as job").wait_for()
    finally:
        page.unroute("**/v1/jobs")
    assert [body["maps"] for body in rerun] == [sent[0]["maps"]]
    for other in api.get("/v1/jobs", params={"scene_id": scene["id"]}).json()["data"]:
        if other["id"] != job["id"]:
            assert api.delete(f"/v1/jobs/{other['id']}").status_code == 204


def test_the_app_ran_under_its_content_security_policy(page: Any, served: dict[str, Any]) -> None:
    """Last in the module: every page above (sign-in, upload, viewer, queries) ran with nothing refused."""
    from service.security_headers import APP_CSP

    assert httpx.get(f"{served['url']}/app").headers["content-security-policy"] == APP_CSP
    assert sorted(set(CSP_VIOLATIONS)) == []  # each kind once
