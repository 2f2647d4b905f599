"""The viewer's first view of a capture looks the way the capture's cameras looked, from behind and above them.

A phone capture of a door, opened from the viewer's fixed direction, showed the door edge-on (77 degrees from the
cameras' mean heading). A run folder whose ``cameras.json`` has every camera looking one horizontal way, opened as
``panogs export-html``'s offline file (the same viewer as ``panogs view`` and the app, its cameras inline), must
open looking that way; a camera kept in the URL still wins.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from run_folder import write_run
from viewer_page import canvas_pixels

from service.viewer.export_html import export_html

pytestmark = pytest.mark.slow  # starts Chromium

# The camera's viewing direction in world coordinates (three.js looks down its -z) and its position.
CAMERA = """() => {
  const cam = window.__panogs.viewer.camera;
  cam.updateMatrixWorld();
  const m = cam.matrixWorld.elements;
  return {look: [-m[8], -m[9], -m[10]], position: cam.position.toArray()};
}"""


def _pose_looking(heading: np.ndarray, up: np.ndarray, position: np.ndarray, down_deg: float) -> list[list[float]]:
    """A camera-to-world pose (OpenCV axes: x right, y down, z forward) looking along ``heading``, pitched down."""
    pitch = np.deg2rad(down_deg)
    forward = np.cos(pitch) * heading - np.sin(pitch) * up
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, position
    return pose.tolist()


def _write_capture(folder: Path, heading: np.ndarray, up: np.ndarray) -> None:
    """Twelve cameras along a line across the scene (points in [0, 4]^3), all looking along ``heading``."""
    side = np.cross(up, heading)
    frames = [
        {"id": f"{k:06d}", "T_world_cam": _pose_looking(heading, up, 2 - 3 * heading + (k - 5.5) * 0.2 * side, 8)}
        for k in range(12)
    ]
    camera = {"width": 160, "height": 120, "fx": 100.0, "fy": 100.0, "cx": 80.0, "cy": 60.0}
    doc = {"camera": camera, "up": up.tolist(), "up_source": "bundle", "frames": frames}
    (folder / "cameras.json").write_text(json.dumps(doc))


def _heading_of(look: np.ndarray, up: np.ndarray) -> np.ndarray:
    flat = look - (look @ up) * up
    return flat / np.linalg.norm(flat)


@pytest.mark.parametrize(
    ("name", "heading", "up"),
    [("z-up", (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)), ("y-up", (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))],
)
def test_first_view_looks_along_the_capture_cameras(
    browser: Any, tmp_path: Path, artifacts: Path, name: str, heading: tuple[float, ...], up: tuple[float, ...]
) -> None:
    folder = tmp_path / "run"
    write_run(folder)
    _write_capture(folder, np.asarray(heading), np.asarray(up))
    out = tmp_path / "offline.html"
    export_html(folder, out)
    kept = [9.0, 2.0, 2.0, 2.0, 2.0, 2.0]  # a URL's camera: on +x, looking at the scene
    page = browser.new_page(viewport={"width": 800, "height": 600})
    try:
        page.goto(out.as_uri())
        page.wait_for_selector(".pgs-viewer[data-state=ready]", timeout=30_000)
        page.wait_for_function("() => window.__panogs.viewer.cameras !== null")  # the look-from list is read
        first = page.evaluate(CAMERA)
        canvas_pixels(page, artifacts / f"viewer-first-view-{name}.png")
        page.goto(out.as_uri() + "#cam=" + ",".join(map(str, kept)))
        page.reload()
        page.wait_for_selector(".pgs-viewer[data-state=ready]", timeout=30_000)
        page.wait_for_function("() => window.__panogs.viewer.cameras !== null")
        from_url = page.evaluate(CAMERA)
    finally:
        page.close()
    up_v, look = np.asarray(up), np.asarray(first["look"])
    angle = np.degrees(np.arccos(np.clip(_heading_of(look, up_v) @ np.asarray(heading), -1, 1)))
    assert angle < 5, f"the first view looks {angle:.0f} degrees away from the cameras' heading"
    assert look @ up_v < -0.3, f"the first view does not look down on the scene (look . up = {look @ up_v:.2f})"
    centre = np.full(3, 2.0)  # the points fill [0, 4]^3: the camera stands behind the cameras, not in front
    assert (np.asarray(first["position"]) - centre) @ np.asarray(heading) < 0
    np.testing.assert_allclose(from_url["position"], kept[:3], atol=1e-6)  # the URL's camera still opens
