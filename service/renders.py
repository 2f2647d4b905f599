"""Renders of a finished job's Gaussian scene from a pose the client sends (``POST /v1/jobs/{id}/render``).

The API process never imports torch (docs/service.md), so a render runs ``panogs render`` in a child process
with the job's folder, the pose written to a temporary file, and one torch thread; the API validates the request
first (with numpy only), so that the child fails only for reasons the client cannot fix. The child needs the
``pipeline`` extra on the API host; without it the endpoint answers 503 with that reason.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from service.errors import InvalidInput, NotFound, ServiceUnavailable

MAX_RENDER_PIXELS = 1920 * 1080  # per render; larger sizes are refused with 422
RENDER_TIMEOUT_S = 120.0  # the child process is killed after this long (503)
LAYERS = ("color", "depth", "depth_vis", "semantic", "instance", "panoptic", "relevance")
Layer = Literal["color", "depth", "depth_vis", "semantic", "instance", "panoptic", "relevance"]


class RenderCamera(BaseModel):
    """Pinhole intrinsics (pixel centres at integer coordinates)."""

    model_config = ConfigDict(extra="forbid")

    width: int = Field(ge=1, le=8192)
    height: int = Field(ge=1, le=8192)
    fx: float = Field(gt=0, allow_inf_nan=False)
    fy: float = Field(gt=0, allow_inf_nan=False)
    cx: float = Field(allow_inf_nan=False)
    cy: float = Field(allow_inf_nan=False)


class RenderCreate(BaseModel):
    """A view of the job's scene: a camera-to-world pose, optionally a camera and a size, and the layer wanted."""

    model_config = ConfigDict(extra="forbid")

    T_world_cam: list[list[float]] = Field(description="4x4 camera-to-world, OpenCV axes (x right, y down, z forward)")
    camera: RenderCamera | None = Field(default=None, description="default: the job's camera")
    width: int | None = Field(default=None, ge=1, le=8192, description="render size; with height")
    height: int | None = Field(default=None, ge=1, le=8192)
    layer: Layer = "panoptic"
    query: str | None = Field(default=None, min_length=1, max_length=200, description="for the relevance layer")

    @model_validator(mode="after")
    def _consistent(self) -> RenderCreate:
        if (self.width is None) != (self.height is None):
            raise ValueError("give both width and height, or neither")
        if self.layer == "relevance" and not self.query:
            raise ValueError("the relevance layer needs a query")
        if len(self.T_world_cam) != 4 or any(len(row) != 4 for row in self.T_world_cam):
            raise ValueError("T_world_cam must be a 4x4 matrix")
        if not all(math.isfinite(v) for row in self.T_world_cam for v in row):
            raise ValueError("T_world_cam holds NaN or infinite values")
        return self


def torch_installed() -> bool:
    """Whether the child process can render (torch importable), checked without importing it."""
    return importlib.util.find_spec("torch") is not None


def check_request(body: RenderCreate, out_dir: Path) -> tuple[int, int]:
    """The render's size; refuses what the child would refuse, with the same messages (422), or 404."""
    from panogs_core.errors import InputError
    from panogs_core.views import parse_camera, parse_pose, run_camera

    try:
        parse_pose(body.T_world_cam, "T_world_cam")
        camera = parse_camera(body.camera.model_dump(), "camera") if body.camera else run_camera(out_dir)[0]
    except InputError as exc:
        if not (out_dir / "cameras.json").is_file():
            raise NotFound("Gaussian scene of job", out_dir.name) from exc
        raise InvalidInput(str(exc)) from exc
    width, height = (body.width, body.height) if body.width and body.height else (camera.width, camera.height)
    if width * height > MAX_RENDER_PIXELS:
        raise InvalidInput(f"size {width}x{height}: a render has at most {MAX_RENDER_PIXELS} pixels")
    if not (out_dir / "gaussians.ply").is_file():
        raise NotFound("Gaussian scene of job", out_dir.name)
    return width, height


def render_layer(body: RenderCreate, out_dir: Path, timeout_s: float = RENDER_TIMEOUT_S) -> bytes:
    """PNG bytes of the requested layer, rendered by ``panogs render`` in a child process.

    Raises:
        InvalidInput: the request is not valid for this job (422).
        NotFound: the job's folder has no Gaussian scene (404).
        ServiceUnavailable: no torch on this host, the child timed out or failed (503).
    """
    width, height = check_request(body, out_dir)
    if not torch_installed():
        raise ServiceUnavailable(
            "renders need the pipeline extra (torch, open3d) on the API host: pip install 'panogs[pipeline]'; "
            "in the docker deployment, rebuild the API image with --build-arg API_KIND=full "
            "(docker compose: PANOGS_API_KIND=full, its default; docs/service.md, Deployment)"
        )
    with tempfile.TemporaryDirectory(prefix="panogs-render-") as tmp:
        pose_file = Path(tmp) / "pose.json"
        doc: dict[str, object] = {"T_world_cam": body.T_world_cam}
        if body.camera is not None:
            doc["camera"] = body.camera.model_dump()
        pose_file.write_text(json.dumps(doc))
        argv = [sys.executable, "-m", "panogs_core.cli", "render", str(out_dir), "--pose", str(pose_file)]
        argv += ["--size", f"{width}x{height}", "--out", str(Path(tmp) / "out")]
        if body.query:
            argv += ["--query", body.query]
        # One thread: renders run beside the API's own work (docs/service.md, one thread per call).
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        try:
            done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s, env=env, check=False)
        except subprocess.TimeoutExpired as exc:
            raise ServiceUnavailable(f"render: no image after {timeout_s:.0f} s") from exc
        if done.returncode == 2:  # a user error, already worded by the CLI
            raise InvalidInput(done.stderr.strip().removeprefix("panogs render: "))
        if done.returncode != 0:
            raise ServiceUnavailable(f"render failed (exit {done.returncode}): {done.stderr.strip()[-500:]}")
        return (Path(tmp) / "out" / f"{body.layer}.png").read_bytes()
