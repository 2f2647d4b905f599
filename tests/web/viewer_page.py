"""What the browser tests do with an open viewer: read its canvas, and put its camera at a key frame's pose."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

BACKGROUND = np.array([16, 20, 24])  # the viewer's clear colour (RGB)


def canvas_pixels(page: Any, path: Path | None = None) -> np.ndarray:  # (H, W, 3) uint8 RGB
    """The viewer's canvas, drawn now (optionally saved as a PNG at ``path``)."""
    page.evaluate("window.__panogs.viewer.renderNow()")
    png = page.locator(".pgs-canvas canvas").screenshot(path=str(path) if path else None)
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return bgr[:, :, ::-1]


def look_from_frame(page: Any, frame: dict[str, Any], camera: dict[str, Any]) -> None:
    """Put the viewer's camera at ``frame``'s pose and vertical field of view (a ``cameras.json`` frame and camera).

    The up vector is the frame's own (minus its y axis: OpenCV's y points down), so a capture held at a tilt is
    seen at that tilt, not levelled to the viewer's up.
    """
    page.evaluate(
        """([pose, fy, height]) => {
          const v = window.__panogs.viewer;
          const cam = v.camera;
          const at = (r, c) => pose[r][c];
          cam.position.set(at(0, 3), at(1, 3), at(2, 3));
          cam.up.set(-at(0, 1), -at(1, 1), -at(2, 1));
          // OpenCV camera: +z looks forward; the orbit target one metre along it.
          v.layer.controls.target.set(at(0, 3) + at(0, 2), at(1, 3) + at(1, 2), at(2, 3) + at(2, 2));
          cam.fov = 2 * Math.atan(height / (2 * fy)) * 180 / Math.PI;
          cam.near = 0.01;
          cam.updateProjectionMatrix();
          v.layer.controls.update();
        }""",
        [frame["T_world_cam"], camera["fy"], camera["height"]],
    )


def frame_in_canvas(canvas: np.ndarray, colour: np.ndarray, camera: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The part of a canvas drawn by ``look_from_frame`` that the frame also sees, and the frame's colour image
    resampled onto those canvas pixels (both (h, w, 3)).

    The canvas has the frame's vertical field of view about its centre, and its own aspect: its centre pixel is
    the frame's principal point (cx, cy), one canvas pixel is height / canvas height frame pixels (times fx / fy
    across). Where the canvas is wider than the frame, only the strip the frame covers is kept; where it is
    narrower, the frame's middle is.
    """
    rows, cols = canvas.shape[:2]
    scale = colour.shape[1] / camera["width"]  # the colour image may be at another resolution than the camera's
    f_canvas = rows * camera["fy"] / camera["height"]  # canvas pixels per unit of the normalised image plane
    fx, fy, cx, cy = (camera[k] * scale for k in ("fx", "fy", "cx", "cy"))
    # canvas column u sees frame column cx + fx * (u - cols / 2) / f_canvas (rows likewise)
    ax, ay = fx / f_canvas, fy / f_canvas
    bx, by = cx - ax * cols / 2, cy - ay * rows / 2
    left = max(0, int(np.ceil(-bx / ax)))
    right = min(cols, int(np.floor((colour.shape[1] - 1 - bx) / ax)) + 1)
    top = max(0, int(np.ceil(-by / ay)))
    bottom = min(rows, int(np.floor((colour.shape[0] - 1 - by) / ay)) + 1)
    crop = canvas[top:bottom, left:right]
    to_frame = np.array([[ax, 0, bx + ax * left], [0, ay, by + ay * top]], np.float64)
    size = (crop.shape[1], crop.shape[0])
    flags = cv2.INTER_AREA | cv2.WARP_INVERSE_MAP
    warped = cv2.warpAffine(np.ascontiguousarray(colour), to_frame, size, flags=flags)
    return crop, warped
