"""``panogs view``'s photo view in a real browser: a bundle run by ``panogs run``, its ``gaussians.ply`` drawn as
splats from a key frame's pose, and compared with that frame's colour image.

By default the bundle is the tiny synthetic room (a short fit). ``PANOGS_PHOTO_BUNDLE=FOLDER`` runs the same test
on any bundle with the default settings, for a real capture: ``panogs import sevenscenes SRC FOLDER --stride 10
--placeholder-maps`` on the 7-Scenes sequence of andyzeng/tsdf-fusion-python (docs/gaussians.md). Its licence keeps
such data and its renders out of the repository and out of CI: the screenshot beside the frame goes to the
git-ignored tests/web/artifacts only.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from service_harness import REPO
from viewer_page import BACKGROUND, canvas_pixels, frame_in_canvas, look_from_frame

pytestmark = pytest.mark.slow

REAL_BUNDLE = os.environ.get("PANOGS_PHOTO_BUNDLE")
# The tiny room's fit is cut short (the labels and the splats' placement are what is tested here; the fit's
# quality has its benchmark); a real capture gets the CPU default, as a user's run would.
TINY_RUN_SETTINGS = ["--set", "appearance.iterations=20"]
COMPARE_SIZE = (96, 72)  # photo and frames are compared at this size: the splats are soft, the frame is sharp


@pytest.fixture(scope="module")
def bundle(synth_tiny: Path) -> Path:
    return Path(REAL_BUNDLE) if REAL_BUNDLE else synth_tiny


@pytest.fixture(scope="module")
def run_dir(bundle: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("view-photo") / "run"
    settings = [] if REAL_BUNDLE else TINY_RUN_SETTINGS
    argv = [sys.executable, "-m", "panogs_core.cli", "run", str(bundle), "--out", str(out), *settings]
    subprocess.run(argv, cwd=REPO, check=True, capture_output=True, timeout=1800)
    return out


@pytest.fixture(scope="module")
def view_url(run_dir: Path) -> Iterator[str]:
    argv = [sys.executable, "-m", "panogs_core.cli", "view", str(run_dir), "--port", "0"]
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


def _small_grey(image_rgb: np.ndarray) -> np.ndarray:
    grey = cv2.cvtColor(np.ascontiguousarray(image_rgb), cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, COMPARE_SIZE, interpolation=cv2.INTER_AREA).astype(np.float64)


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two grey images: the layout agrees, whatever the exposure and the white balance."""
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum() + 1e-12))


def _colour(bundle: Path, frame_id: str) -> np.ndarray:  # RGB
    scene = json.loads((bundle / "scene.json").read_text())
    path = next(f["color"] for f in scene["frames"] if f["id"] == frame_id)
    return cv2.imread(str(bundle / path))[:, :, ::-1]


def test_photo_view_from_a_key_frame_looks_like_that_frame(
    browser: Any, view_url: str, run_dir: Path, bundle: Path, artifacts: Path
) -> None:
    cameras = json.loads((run_dir / "cameras.json").read_text())
    frames, camera = cameras["frames"], cameras["camera"]
    context = browser.new_context(viewport={"width": 960, "height": 720})
    page = context.new_page()
    try:
        page.goto(f"{view_url}#mode=camera")
        page.wait_for_selector(".pgs-viewer[data-state=ready]", timeout=120_000)
        page.keyboard.press("p")
        page.wait_for_selector(".pgs-viewer[data-photo=on]", timeout=120_000)
        look_from_frame(page, frames[0], camera)
        page.wait_for_timeout(1500)  # the splats' depth order comes from Spark's worker a few frames later
        canvas = canvas_pixels(page)
    finally:
        context.close()
    photo, colour = frame_in_canvas(canvas, _colour(bundle, str(frames[0]["id"])), camera)
    cv2.imwrite(str(artifacts / "view-photo-beside-colour-frame.png"), np.hstack([photo, colour])[:, :, ::-1])
    # No holes: the splats cover the frame's view (the viewer's clear colour shows through nowhere much).
    holes = (np.abs(photo.astype(int) - BACKGROUND).sum(axis=2) <= 12).mean()
    assert holes < 0.05, f"{holes:.1%} of the frame's view shows the background"
    # The layout is the frame's: closer to its own colour image than to any other key frame's (a render at a
    # wrong pose, mirrored or upside down, or of dots would match another frame as well or better).
    own = _correlation(_small_grey(photo), _small_grey(colour))
    others = [
        _correlation(_small_grey(photo), _small_grey(frame_in_canvas(canvas, _colour(bundle, str(f["id"])), camera)[1]))
        for f in frames[1:]
        if np.linalg.norm(np.asarray(f["T_world_cam"])[:3, 3] - np.asarray(frames[0]["T_world_cam"])[:3, 3]) > 0.5
    ]
    assert others, "no key frame half a metre away to compare with"
    print(
        f"photo from frame {frames[0]['id']}: correlation {own:.3f} with it, {max(others):.3f} with the best of "
        f"{len(others)} other key frames; background {holes:.2%}"
    )
    assert own > 0.5, f"correlation with the frame: {own:.2f}"
    assert own > max(others) + 0.1, f"own frame {own:.2f}, best other {max(others):.2f}"
