"""Renders of a finished job's Gaussian scene from a pose the client sends (``POST /v1/jobs/{id}/render``).

The API process never imports torch (docs/service.md), so a render runs ``panogs render`` in a child process
with the job's folder, the pose written to a temporary file, and one torch thread; the API validates the request
first (with numpy only), so that the child fails only for reasons the client cannot fix. The child needs the
``pipeline`` extra on the API host; without it the endpoint answers 503 with that reason.

Every number of a request is checked against a stated range (docs/service.md, "Renders"): a focal length within
``FOCAL_RANGE`` times the image's larger side, a principal point within one image size around the image, a proper
rotation and a translation of at most ``MAX_TRANSLATION_M``. Outside them the rasterizer's arithmetic overflows, so
such a view has no image worth drawing; it is a 422 naming the field. A child that fails anyway is logged here with
its stderr under a request id, and the client gets that id, never the child's traceback or a path.

The ranges bound a render's size, not its work: a wide field of view with the principal point far outside the
image (every value in range) spread near Gaussians over the whole image and burned 120 s of CPU. So the child
also runs under a CPU budget (``RENDER_CPU_S``, the kernel's ``RLIMIT_CPU``), and :class:`RenderSlots` lets a
tenant hold at most ``RENDERS_PER_TENANT`` renders at once (429 with ``Retry-After`` past that).
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from service.errors import InvalidInput, NotFound, ServiceUnavailable, TooManyRequests, sanitize_message

logger = logging.getLogger(__name__)

MAX_RENDER_PIXELS = 1920 * 1080  # per render; larger sizes are refused with 422
RENDER_TIMEOUT_S = 120.0  # the child process is killed after this long (503)
# CPU seconds a render may use: a 1920 x 1080 render of a ScanNet-size scene takes 2-6 s on one thread; the
# budget is far above that and far below what one request could take from the API host's cores.
RENDER_CPU_S = 30
RENDERS_PER_TENANT = 2  # renders one tenant may have running at once
RENDER_RETRY_AFTER_S = 2
FOCAL_RANGE = (0.02, 200.0)  # fx, fy per pixel of the larger side: fields of view from about 176 to 0.3 degrees
MAX_TRANSLATION_M = 1e5  # a camera farther than 100 km from the scene's origin is refused
ROTATION_TOLERANCE = 1e-3  # R @ R.T may differ from the identity by this much per entry
RENDER_MODULE = "panogs_core.cli"  # run as `python -m RENDER_MODULE render ...`
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

    @field_validator("fx", "fy")
    @classmethod
    def _plausible_focal(cls, value: float, info: ValidationInfo) -> float:
        side = max(info.data.get("width", 1), info.data.get("height", 1))
        low, high = FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side
        if not low <= value <= high:
            raise ValueError(
                f"{value!r} is outside [{low:g}, {high:g}] ({FOCAL_RANGE[0]:g} to {FOCAL_RANGE[1]:g} times the "
                f"image's larger side of {side} pixels)"
            )
        return value

    @field_validator("cx", "cy")
    @classmethod
    def _principal_point_near_the_image(cls, value: float, info: ValidationInfo) -> float:
        size = info.data.get("width" if info.field_name == "cx" else "height", 1)
        if not -size <= value <= 2 * size:
            raise ValueError(f"{value!r} is outside [{-size}, {2 * size}] (one image size around the image of {size})")
        return value


class RenderCreate(BaseModel):
    """A view of the job's scene: a camera-to-world pose, optionally a camera and a size, and the layer wanted."""

    model_config = ConfigDict(extra="forbid")

    # The shape is in the schema; that the matrix is rigid is checked by the validator below (JSON Schema cannot).
    T_world_cam: list[list[float]] = Field(
        description="4x4 camera-to-world, OpenCV axes (x right, y down, z forward); a rigid transform",
        json_schema_extra={
            "minItems": 4,
            "maxItems": 4,
            "items": {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4},
        },
    )
    camera: RenderCamera | None = Field(default=None, description="default: the job's camera")
    width: int | None = Field(default=None, ge=1, le=8192, description="render size; with height")
    height: int | None = Field(default=None, ge=1, le=8192)
    layer: Layer = "panoptic"
    query: str | None = Field(default=None, min_length=1, max_length=200, description="for the relevance layer")

    @field_validator("query")
    @classmethod
    def _query_is_text(cls, value: str | None) -> str | None:
        # The query reaches the child as an argument: a NUL cannot be in one, and a query without a word (such as
        # "--", which argparse takes for its end-of-options marker) means nothing to any encoder.
        if value is not None and not value.isprintable():
            raise ValueError("the query holds control characters; send printable text")
        if value is not None and not any(ch.isalnum() for ch in value):
            raise ValueError(f"the query {value!r} has no letter or digit")
        return value

    @model_validator(mode="after")
    def _consistent(self) -> RenderCreate:
        if (self.width is None) != (self.height is None):
            raise ValueError("give both width and height, or neither")
        if self.layer == "relevance" and not self.query:
            raise ValueError("the relevance layer needs a query")
        return self

    @field_validator("T_world_cam")
    @classmethod
    def _rigid_pose(cls, value: list[list[float]]) -> list[list[float]]:
        if len(value) != 4 or any(len(row) != 4 for row in value):
            raise ValueError("T_world_cam must be a 4x4 matrix")
        if not all(math.isfinite(v) for row in value for v in row):
            raise ValueError("T_world_cam holds NaN or infinite values")
        pose = np.asarray(value, dtype=np.float64)
        rotation, translation = pose[:3, :3], pose[:3, 3]
        orthonormal = np.allclose(rotation @ rotation.T, np.eye(3), atol=ROTATION_TOLERANCE)
        if not np.allclose(pose[3], [0, 0, 0, 1]) or not orthonormal or np.linalg.det(rotation) <= 0:
            raise ValueError(
                "not a rigid transform: the rotation must be orthonormal with determinant +1 (tolerance "
                f"{ROTATION_TOLERANCE:g}) and the last row 0 0 0 1"
            )
        distance = float(np.linalg.norm(translation))
        if distance > MAX_TRANSLATION_M:
            raise ValueError(f"the translation is {distance:.6g} m from the origin; at most {MAX_TRANSLATION_M:g} m")
        return value


def torch_installed() -> bool:
    """Whether the child process can render (torch importable), checked without importing it."""
    return importlib.util.find_spec("torch") is not None


def check_request(body: RenderCreate, out_dir: Path) -> tuple[int, int]:
    """The render's size; refuses what the child would refuse, with the same messages (422), or 404."""
    from panogs_core.errors import InputError
    from panogs_core.gaussians.views import parse_camera, parse_pose, run_camera
    from panogs_core.io.run_folder import CAMERAS_JSON, GAUSSIANS_PLY

    try:
        parse_pose(body.T_world_cam, "T_world_cam")
        camera = parse_camera(body.camera.model_dump(), "camera") if body.camera else run_camera(out_dir)[0]
    except InputError as exc:
        if not CAMERAS_JSON.path(out_dir).is_file():
            raise NotFound("Gaussian scene of job", out_dir.name) from exc
        raise InvalidInput(str(exc)) from exc
    width, height = (body.width, body.height) if body.width and body.height else (camera.width, camera.height)
    if width * height > MAX_RENDER_PIXELS:
        raise InvalidInput(f"size {width}x{height}: a render has at most {MAX_RENDER_PIXELS} pixels")
    if not GAUSSIANS_PLY.path(out_dir).is_file():
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
        argv = [sys.executable, "-m", RENDER_MODULE, "render", str(out_dir), "--pose", str(pose_file)]
        argv += ["--size", f"{width}x{height}", "--out", str(Path(tmp) / "out")]
        if body.query:
            argv.append(f"--query={body.query}")  # one token: a query that starts with "-" is not an option
        # One thread: renders run beside the API's own work (docs/service.md, one thread per call).
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        done = _run_child(argv, env, timeout_s)
        if done.returncode == 2:  # a user error, already worded by the CLI; its paths are ours, not the client's
            message = done.stderr.strip().removeprefix("panogs render: ").replace(str(pose_file), "the request")
            raise InvalidInput(sanitize_message(message, [out_dir]))
        if done.returncode != 0:
            raise _child_failed(done.returncode, done.stderr, out_dir)
        return (Path(tmp) / "out" / f"{body.layer}.png").read_bytes()


def _run_child(argv: list[str], env: dict[str, str], timeout_s: float) -> subprocess.CompletedProcess[str]:
    """Run the render child under the CPU budget; 503 when it outlives ``timeout_s`` or its budget."""
    with subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) as child:
        _limit_cpu(child.pid)
        try:
            stdout, stderr = child.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired as exc:
            child.kill()
            child.communicate()
            raise ServiceUnavailable(f"render: no image after {timeout_s:.0f} s") from exc
    if child.returncode in (-signal.SIGXCPU, -signal.SIGKILL) and _cpu_limited():
        raise ServiceUnavailable(
            f"render: over its CPU budget of {RENDER_CPU_S} s; a smaller size or a narrower field of view costs less"
        )
    return subprocess.CompletedProcess(argv, child.returncode, stdout, stderr)


def _cpu_limited() -> bool:
    return hasattr(resource, "prlimit")


def _limit_cpu(pid: int) -> None:
    """Cap the child's CPU seconds (SIGXCPU at the soft limit, SIGKILL one second later), where the OS allows.

    Set on the running child (``prlimit``) rather than in ``preexec_fn``, which is unsafe in a threaded server.
    The child has not imported torch yet when this runs; the interpreter's start is inside the budget.
    """
    if _cpu_limited():
        with contextlib.suppress(ProcessLookupError):  # it already ended
            resource.prlimit(pid, resource.RLIMIT_CPU, (RENDER_CPU_S, RENDER_CPU_S + 1))


class RenderSlots:
    """At most ``per_tenant`` renders of one tenant at once in this process; the next one is a 429."""

    def __init__(self, per_tenant: int = RENDERS_PER_TENANT) -> None:
        self.per_tenant = per_tenant
        self._running: dict[uuid.UUID, int] = {}
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def hold(self, tenant_id: uuid.UUID) -> Iterator[None]:
        with self._lock:
            if self._running.get(tenant_id, 0) >= self.per_tenant:
                raise TooManyRequests(
                    f"{self.per_tenant} renders of this account are running; retry when one ends",
                    retry_after_s=RENDER_RETRY_AFTER_S,
                )
            self._running[tenant_id] = self._running.get(tenant_id, 0) + 1
        try:
            yield
        finally:
            with self._lock:
                self._running[tenant_id] -= 1
                if not self._running[tenant_id]:
                    del self._running[tenant_id]


def _child_failed(returncode: int, stderr: str, out_dir: Path) -> ServiceUnavailable:
    """The 503 for a render child that crashed: its stderr goes to the server log under a request id, the client
    is told that id (a traceback names our source files and the job's folder)."""
    request_id = uuid.uuid4().hex[:12]
    logger.error(
        "render of %s failed (exit %s, request %s); its stderr:\n%s", out_dir, returncode, request_id, stderr[-20000:]
    )
    return ServiceUnavailable(f"render failed (exit {returncode}, request {request_id}); see the server log")
