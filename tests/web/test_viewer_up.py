"""The viewer's first view and orbit follow the run's up: the tiny room captured in a world tilted 55 degrees (a
TUM sequence, which records no gravity), imported, run, and opened with ``panogs view``, shows the room upright,
with a level horizon that stays level while the user orbits."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from capture_room import TILTED_55
from service_harness import REPO
from viewer_page import canvas_pixels

pytestmark = pytest.mark.slow

TILT = TILTED_55

# The camera's axes in world coordinates (three.js: x right, y up on the screen, looking down -z).
CAMERA_AXES = """() => {
  const cam = window.__panogs.viewer.camera;
  cam.updateMatrixWorld();
  const m = cam.matrixWorld.elements;
  return {up: cam.up.toArray(), right: [m[0], m[1], m[2]], screenUp: [m[4], m[5], m[6]],
          back: [m[8], m[9], m[10]]};
}"""


@pytest.fixture(scope="module")
def tilted_run(tilted_tum_run: Path) -> Path:
    """The tilted capture's run (the session's, shared with tests/core/test_up_direction.py: only read)."""
    return tilted_tum_run / "run"


@pytest.fixture(scope="module")
def view_url(tilted_run: Path) -> Iterator[str]:
    argv = [sys.executable, "-m", "panogs_core.cli", "view", str(tilted_run), "--port", "0"]
    proc = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        found = re.search(r"http://127\.0\.0\.1:\d+/", line)
        assert found is not None, line
        yield found.group(0)
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def _assert_upright(axes: dict[str, list[float]], up: np.ndarray, where: str) -> None:
    right, screen_up = np.asarray(axes["right"]), np.asarray(axes["screenUp"])
    assert abs(right @ up) < 1e-3, f"{where}: the horizon is rolled (right . up = {right @ up:.3f})"
    assert screen_up @ up > 0.1, f"{where}: the room is upside down or seen edge-on ({screen_up @ up:.3f})"


def test_first_view_of_a_tilted_capture_is_upright_and_stays_so(
    browser: Any, view_url: str, tilted_run: Path, artifacts: Path
) -> None:
    cameras = json.loads((tilted_run / "cameras.json").read_text())
    up = np.asarray(cameras["up"])
    context = browser.new_context(viewport={"width": 960, "height": 720})
    page = context.new_page()
    try:
        page.goto(view_url)
        page.wait_for_selector(".pgs-viewer[data-state=ready]", timeout=120_000)
        first = page.evaluate(CAMERA_AXES)
        canvas_pixels(page, artifacts / "viewer-tilted-capture-first-view.png")
        np.testing.assert_allclose(first["up"], up, atol=1e-6)  # the run's up is the camera's
        _assert_upright(first, up, "first view")
        assert np.asarray(first["back"]) @ up > 0.1, "the first view is not from above"
        box = page.locator(".pgs-canvas canvas").bounding_box()
        assert box is not None
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        page.mouse.move(x, y)
        page.mouse.down()
        page.mouse.move(x + 200, y + 60, steps=8)  # orbit around and a little over
        page.mouse.up()
        orbited = page.evaluate(CAMERA_AXES)
        canvas_pixels(page, artifacts / "viewer-tilted-capture-orbited.png")
        # A frame the import's stride left out is in the "look from" list, marked, and looks from its own pose.
        skipped = next(f for f in cameras["frames"] if f.get("skipped"))
        choose = page.locator("select[data-role=frame]")
        label = choose.locator(f"option[value='{skipped['id']}']").text_content()
        choose.select_option(str(skipped["id"]))
        position = page.evaluate("() => window.__panogs.viewer.camera.position.toArray()")
    finally:
        context.close()
    assert np.linalg.norm(np.asarray(orbited["right"]) - first["right"]) > 0.1, "the drag did not orbit"
    _assert_upright(orbited, up, "after an orbit")
    assert label == f"frame {skipped['id']} (not in the bundle)"
    np.testing.assert_allclose(position, np.asarray(skipped["T_world_cam"])[:3, 3], atol=1e-6)
