"""The viewer's binary scene, ``panogs view``'s server and ``panogs export-html``'s offline file."""

from __future__ import annotations

import base64
import json
import re
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from run_folder import write_run

from panogs_core.errors import InputError
from panogs_core.io.run_folder import load_result
from panogs_core.palette import CLASS_PALETTE, instance_color
from service.job_results import run_query
from service.schemas import QueryCreate
from service.viewer.export_html import export_html
from service.viewer.scene import build_scene, decode, point_radii


@pytest.fixture
def run(tmp_path: Path) -> tuple[Path, dict[str, Any]]:
    folder = tmp_path / "run"
    return folder, write_run(folder)


def test_scene_round_trips_every_array(run: tuple[Path, dict[str, Any]]) -> None:
    folder, source = run
    header, arrays = decode(build_scene(folder).data)
    assert header["count"] == header["total"] == 60
    np.testing.assert_array_equal(arrays["position"], source["points"])
    np.testing.assert_array_equal(arrays["semantic"], source["semantic"])
    np.testing.assert_array_equal(arrays["instance"], source["instance"])
    np.testing.assert_allclose(arrays["scale"], source["scale"], rtol=1e-5)
    assert np.abs(arrays["color"].astype(int) - np.round(source["colors"] * 255)).max() <= 1
    assert [c["count"] for c in header["classes"]] == [np.sum(source["semantic"] == k) for k in range(3)]
    assert header["void"]["count"] == 5
    assert header["classes"][1]["color"] == list(CLASS_PALETTE[1])
    assert [i["color"] for i in header["instances"]] == [list(instance_color(k)) for k in range(3)]
    for spec in header["arrays"].values():
        assert spec["offset"] % 4 == 0  # the browser maps typed arrays without copying


def test_a_fitted_scene_draws_its_points_no_larger_than_their_spacing(tmp_path: Path) -> None:
    # A surface sampled every 5 cm whose Gaussians the fit grew to 20 cm (max_scale_growth lets them): drawn at
    # their fitted size the points were big overlapping discs; capped, at the radius the fit started from.
    grid = np.stack(np.meshgrid(np.arange(20) * 0.05, np.arange(20) * 0.05, [0.0]), -1).reshape(-1, 3)
    position = grid.astype(np.float32)
    spacing_radius = np.sqrt(0.05 * 0.05**2)  # gaussian_log_scales: sqrt(point_size * mean squared 3-NN distance)
    grown = np.full((len(position), 3), np.log(0.2), np.float32)
    radii = point_radii(position, grown)
    inner = (np.abs(grid[:, :2] - 0.475) < 0.4).all(axis=1)  # away from the border: four neighbours at 5 cm
    np.testing.assert_allclose(radii[inner], spacing_radius, rtol=1e-4)
    small = np.full((len(position), 3), np.log(0.001), np.float32)  # smaller than the spacing: kept
    np.testing.assert_allclose(point_radii(position, small), 0.001, rtol=1e-4)
    flat = np.log(np.tile([0.002, 0.002, 0.0005], (len(position), 1))).astype(np.float32)  # mean of the axes
    np.testing.assert_allclose(point_radii(position, flat), 0.0015, rtol=1e-4)


def test_decimation_keeps_a_seeded_subset_with_its_labels(run: tuple[Path, dict[str, Any]]) -> None:
    folder, source = run
    first, second = build_scene(folder, max_primitives=10), build_scene(folder, max_primitives=10)
    assert first.data == second.data
    header, arrays = decode(first.data)
    assert (header["count"], header["total"]) == (10, 60)
    rows = {tuple(p): i for i, p in enumerate(source["points"].tolist())}
    kept = [rows[tuple(p)] for p in arrays["position"].tolist()]
    np.testing.assert_array_equal(arrays["instance"], source["instance"][kept])


def test_missing_file_is_named(run: tuple[Path, dict[str, Any]]) -> None:
    folder, _ = run
    (folder / "gaussians.ply").unlink()
    with pytest.raises(InputError, match=r"gaussians\.ply: missing"):
        build_scene(folder)


def _inline_scene(page: str) -> bytes:
    match = re.search(r'<script id="panogs-scene" type="application/octet-stream">([^<]*)</script>', page)
    assert match is not None
    return base64.b64decode(match.group(1))


def test_export_html_is_self_contained_and_answers_class_queries(
    run: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    folder, _ = run
    out = tmp_path / "scene.html"
    stats = export_html(folder, out, max_primitives=20)
    page = out.read_text()
    assert stats == {"count": 20, "total": 60, "bytes": len(page.encode())}
    assert not re.search(r"<(script|link)[^>]+(src|href)=", page)  # nothing loaded from anywhere
    header, _ = decode(_inline_scene(page))
    assert "cameras" not in header  # this run has no cameras.json
    cameras = {"camera": {"fy": 100.0, "height": 120}, "frames": [{"id": "f0", "T_world_cam": np.eye(4).tolist()}]}
    (folder / "cameras.json").write_text(json.dumps(cameras))
    export_html(folder, out, max_primitives=20)
    header, _ = decode(_inline_scene(out.read_text()))
    assert header["cameras"] == cameras  # the "look from" list works offline too
    result = load_result(folder)
    for name in ("wall", "chair", "table"):
        api = run_query(result, QueryCreate(text=name), None).model_dump(mode="json")
        assert header["class_queries"][name]["hits"] == api["hits"]


def test_export_html_over_the_size_limit_names_both_limits(run: tuple[Path, dict[str, Any]], tmp_path: Path) -> None:
    folder, _ = run
    out = tmp_path / "big.html"
    with pytest.raises(InputError, match=r"over the limit of 1,000 .*--max-primitives"):
        export_html(folder, out, max_bytes=1000)
    assert not out.exists()


def test_local_viewer_serves_the_scene_and_the_api_query(run: tuple[Path, dict[str, Any]]) -> None:
    from service.viewer.local import RunViewer, serve

    folder, _ = run
    viewer = RunViewer(folder)
    ready = threading.Event()
    urls: list[str] = []
    thread = threading.Thread(target=serve, args=(viewer, 0, lambda u: (urls.append(u), ready.set())), daemon=True)
    thread.start()
    assert ready.wait(10)
    with httpx.Client(base_url=urls[0], timeout=10) as client:
        assert client.get("scene.bin").content == viewer.scene.data
        assert "static/view.js" in client.get("").text
        assert client.get("gaussians.ply").content == (folder / "gaussians.ply").read_bytes()
        assert client.get("cameras.json").status_code == 404  # none in this run: the viewer shows no frame list
        cameras = {"camera": {"fy": 100.0, "height": 120}, "frames": [{"id": "f0", "T_world_cam": np.eye(4).tolist()}]}
        (folder / "cameras.json").write_text(json.dumps(cameras))
        assert client.get("cameras.json").json() == cameras
        answer = client.post("query", json={"text": "chair", "top_k": 2}).json()
        expected = run_query(load_result(folder), QueryCreate(text="chair", top_k=2), None)
        assert answer["hits"] == expected.model_dump(mode="json")["hits"]
        # The best of the rest, under the threshold, with their scores; a lower threshold makes them hits.
        assert [c["class_name"] for c in answer["candidates"]] == ["wall", "table"]  # equal scores: lower id first
        assert answer["min_score"] == 0.5
        assert all(c["score"] < 0.5 for c in answer["candidates"])
        lowered = client.post("query", json={"text": "chair", "min_score": 0.0}).json()
        assert [h["class_name"] for h in lowered["hits"]] == ["chair", "wall", "table"]
        assert lowered["candidates"] == []
        refused = client.post("query", json={"text": "chair", "bogus": 1})
        assert refused.status_code == 422
        assert any("bogus" in p for p in refused.json()["problems"])
        assert client.get("static/../../settings.py").status_code == 404


def test_panogs_view_prints_its_url(run: tuple[Path, dict[str, Any]]) -> None:
    folder, _ = run
    argv = [sys.executable, "-m", "panogs_core.cli", "view", str(folder), "--port", "0"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        url = re.search(r"http://127\.0\.0\.1:\d+/", line)
        assert url is not None, line
        assert httpx.get(url.group(0) + "scene.bin", timeout=10).content[:4] == b"PGSV"
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_panogs_view_says_nothing_when_a_tab_leaves_mid_answer(
    run: tuple[Path, dict[str, Any]], capsys: pytest.CaptureFixture[str]
) -> None:
    from service.viewer.local import RunViewer, make_server

    folder, _ = run
    server = make_server(RunViewer(folder), 0)
    try:
        for gone in (BrokenPipeError(32, "Broken pipe"), ConnectionResetError(104, "Connection reset by peer")):
            try:
                raise gone
            except OSError:
                server.handle_error(None, ("127.0.0.1", 1))
        assert capsys.readouterr().err == ""
        try:
            raise ValueError("a real fault")
        except ValueError:
            server.handle_error(None, ("127.0.0.1", 1))
        assert "ValueError: a real fault" in capsys.readouterr().err  # other faults still show
    finally:
        server.server_close()


@pytest.mark.slow  # starts Chromium
def test_offline_file_opens_in_the_browser_and_answers_a_class(
    run: tuple[Path, dict[str, Any]], tmp_path: Path, browser: Any
) -> None:
    folder, _ = run
    out = tmp_path / "offline.html"
    export_html(folder, out)
    page = browser.new_page()
    try:
        page.goto(out.as_uri())
        page.wait_for_selector(".pgs-viewer[data-state=ready]", timeout=30_000)
        page.fill(".pgs-query input", "chair")
        page.press(".pgs-query input", "Enter")
        page.wait_for_selector(".pgs-viewer[data-query=done]")
        hits = json.loads(
            page.evaluate("JSON.stringify([...document.querySelectorAll('[data-hit-id]')].map(e => +e.dataset.hitId))")
        )
        answer = run_query(load_result(folder), QueryCreate(text="chair"), None)
        assert hits == [h.instance_id for h in answer.hits]
        below = page.locator("[data-candidate-id]").evaluate_all("els => els.map(e => +e.dataset.candidateId)")
        assert below == [c.instance_id for c in answer.candidates]
        assert below, "the file carries the closest instances under the threshold too"
        assert not page.locator("[data-role=threshold]").is_visible()  # its answers are stored at one threshold
        # Free text is refused offline; the last answer's hits go with the refusal.
        page.fill(".pgs-query input", "something soft to sit on")
        page.press(".pgs-query input", "Enter")
        page.wait_for_selector(".pgs-viewer[data-query=error]")
        assert "free text needs `panogs view`" in page.inner_text(".pgs-query-status")
        assert page.locator("[data-hit-id], [data-candidate-id]").count() == 0
        assert not page.get_attribute(".pgs-viewer", "data-lit")
    finally:
        page.close()


def test_the_header_carries_the_runs_up_from_cameras_json(run: tuple[Path, dict[str, Any]]) -> None:
    folder, _ = run
    assert "up" not in decode(build_scene(folder).data)[0]  # an older run: the viewer keeps z up
    cameras = {"camera": {"fy": 100.0, "height": 120}, "up": [0, 2, 0], "frames": []}
    (folder / "cameras.json").write_text(json.dumps(cameras))
    assert decode(build_scene(folder).data)[0]["up"] == [0.0, 1.0, 0.0]
    (folder / "cameras.json").write_text(json.dumps({**cameras, "up": [0, 0, 0]}))
    with pytest.raises(InputError, match=r"cameras\.json: up: expected 3 finite numbers"):
        build_scene(folder)
