"""The service's boundary against hostile input (the standing defence).

Every route that takes user data is fed generated bad input (hypothesis, derandomized and bounded: a fixed
number of examples per route, no shrinking, so that a run takes the same time and finds the same things on
every machine) and the known attacks by name. Each answer must be:

- a 4xx with a JSON ``{"type", "message"}`` body, never a 5xx (a request that is valid may succeed);
- free of tracebacks and of absolute host paths (the storage root, the test's folders, ``/etc``, ``/tmp`` ...;
  what the request itself sent may be echoed);
- made without reading outside the tenant's storage: a request that names a host file or another tenant's
  file is refused before a job exists, and the other tenant's class names never appear in an answer;
- clean: after a refusal the storage holds exactly what it held before (and the database no new row).

The world (two tenants, each with a scene and a finished job) is built once per module on the embedded SQLite
database, what a new user runs; the named cases about job requests run on PostgreSQL as well.

On the code before the hostile-input hardening these fail: a vocabulary that is a path was accepted, deep or
huge JSON was a 500, render numbers gave a traceback in a 503, a 422 showed the storage path, images were decoded
before their header was read (cv2 raising on huge declared sizes: 500), uploads had no free-disk check and answers
had no security headers. The suite found three more classes: a NUL character in a stored text (job vocabulary,
scene name, upload filename) is a 500 on PostgreSQL, a .npy header whose shape overflows int64 is accepted or a
500, and a PLY vertex count of thousands of digits is a 500.
"""

from __future__ import annotations

import base64
import json
import tracemalloc
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pytest
from fastapi.testclient import TestClient
from gaussian_runs import opaque_gaussians
from hostile_inputs import (
    HOST_PATHS,
    BadBundle,
    Damage,
    ExtraMember,
    Image,
    JsonText,
    Link,
    RawField,
    WholeFile,
    WrongType,
    damages,
    header_values,
    host_path_leaks,
    hostile_body,
    hostile_json_values,
    huge_integer,
    nested_json,
    npy_header,
    pack_members,
    read_members,
    traceback_markers,
)
from hypothesis import HealthCheck, Phase, example, given, note
from hypothesis import settings as hypothesis_settings
from hypothesis import strategies as st
from svc_helpers import RecordingSender, edit_manifest, mark_succeeded, new_key, upload_bytes, write_tiny_bundle

from panogs_core.gaussians.ply import write_gaussian_ply
from panogs_core.gaussians.views import write_cameras
from panogs_core.stages.export import write_vocabulary
from panogs_core.types import Camera, Frame, Vocabulary
from service.api_app import create_app
from service.db.migrate import upgrade
from service.db.models import Job, Upload
from service.db.session import get_engine, get_session_factory, session_scope
from service.settings import Settings
from service.storage import Storage

# Bounded and reproducible: the same examples on every run, no shrinking (a failure prints the drawn example,
# whose repr says what it is), no example database written into the checkout.
BOUNDED = hypothesis_settings(
    max_examples=20,
    deadline=None,
    derandomize=True,
    database=None,
    phases=(Phase.explicit, Phase.generate),
    suppress_health_check=list(HealthCheck),
)
FEW = hypothesis_settings(BOUNDED, max_examples=10)

Response = Any  # the TestClient's response (starlette's own httpx build), read as httpx.Response
SECRET_CLASSES = ("alice_secret_sofa", "alice_secret_lamp", "alice_secret_rug")  # only tenant A's bundle has them
FEATURE_DIM = 8
JSON_HEADERS = {"Content-Type": "application/json"}
OCTET = "application/offset+octet-stream"
CAMERA = Camera(width=32, height=24, fx=24.0, fy=24.0, cx=15.5, cy=11.5)


# -- the world ---------------------------------------------------------------------------------------------------


@dataclass(repr=False)  # hypothesis prints its arguments; the bundle's bytes would fill the report
class World:
    """Two tenants on one app: A (alice) holds the secret vocabulary, B (mallory) is the hostile one."""

    client: TestClient
    settings: Settings
    alice: dict[str, str]
    mallory: dict[str, str]
    alice_scene: str
    mallory_scene: str
    mallory_job: str
    alice_vocabulary: Path  # absolute path of A's vocabulary.json in the storage
    valid_members: dict[str, bytes]  # a valid bundle's files, for the damages to break
    tmp: Path

    @property
    def storage(self) -> Path:
        return self.settings.storage

    @property
    def known_paths(self) -> list[str]:
        """Absolute paths of this host that no answer may contain."""
        return [str(self.storage), str(self.tmp), str(Path(__file__).resolve().parents[2])]

    @property
    def alice_paths(self) -> list[str]:
        """Ways to name A's vocabulary.json: absolute, relative to the storage, and escaping a bundle folder."""
        rel = self.alice_vocabulary.relative_to(self.storage).as_posix()
        return [str(self.alice_vocabulary), rel, f"../../{rel}", f"storage/{rel}", f"file://{self.alice_vocabulary}"]


def _write_finished_result(out_dir: Path, names: tuple[str, ...]) -> None:
    """A finished run's folder (what queries and renders read): one instance, a vocabulary, a Gaussian wall."""
    out_dir.mkdir(parents=True, exist_ok=True)
    xs, ys = np.meshgrid(np.arange(-1.5, 1.5, 0.1), np.arange(-1.2, 1.2, 0.1))
    means = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 2.0)], 1).astype(np.float32)
    n = len(means)
    zeros = np.zeros(n, np.int64)
    scene = opaque_gaussians(means, np.tile([0.9, 0.1, 0.1], (n, 1)), 0.1)
    write_gaussian_ply(out_dir / "gaussians.ply", scene, np.zeros((n, 3), np.float32), zeros, zeros - 1)
    write_cameras(out_dir / "cameras.json", CAMERA, [Frame(id="f0", T_world_cam=np.eye(4), depth="d.png")])
    embeddings = np.eye(len(names), FEATURE_DIM, dtype=np.float32)
    kinds: tuple[Literal["thing", "stuff"], ...] = tuple("stuff" for _ in names)
    write_vocabulary(out_dir, Vocabulary(names=names, kinds=kinds, embeddings=embeddings), "t")
    instance = {"id": 0, "class_index": 0, "class_name": names[0], "kind": "stuff", "score": 0.9, "num_points": n}
    instance.update(centroid=[0, 0, 2], bbox_min=[-1.5, -1.2, 2], bbox_max=[1.5, 1.2, 2])
    (out_dir / "instances.json").write_text(json.dumps([instance]))
    np.save(out_dir / "instance_features.npy", embeddings[:1])


def _secret_vocabulary(root: Path) -> None:
    doc = json.loads((root / "vocabulary.json").read_text())
    for entry, name in zip(doc["classes"], SECRET_CLASSES):
        entry["name"] = name
    (root / "vocabulary.json").write_text(json.dumps(doc))


def _settings(tmp: Path, backend: str, **overrides: Any) -> Settings:
    # No stand-in pipeline: jobs are only created here, never run, and their config is checked by the real
    # PipelineConfig.
    values: dict[str, Any] = {
        "data_dir": tmp / "data",
        "api_key_cache_s": 0,
        "status_cache_s": 0,
        "query_encoder": "off",  # free text needs no encoder process: it is refused (422) unless it is a class
        "quota_concurrent_jobs": None,
        "max_upload_bytes": 50_000_000,
    }
    if backend == "sqlite":
        (tmp / "data").mkdir(parents=True, exist_ok=True)
        upgrade(f"sqlite:///{tmp / 'data' / 'panogs.db'}")
    values.update(overrides)
    return Settings(_env_file=None, **values)  # type: ignore[call-arg]


def _build_world(client: TestClient, settings: Settings, tmp: Path) -> World:
    alice, mallory = new_key(settings, "alice"), new_key(settings, "mallory")
    scenes = {}
    for who, key, mutate in (("alice", alice, _secret_vocabulary), ("mallory", mallory, None)):
        data = _pack(write_tiny_bundle(tmp / f"bundle-{who}", mutate=mutate))
        upload = upload_bytes(client, key, data, filename=f"{who}.zip")
        response = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=key)
        assert response.status_code == 201, response.text
        scenes[who] = response.json()["id"]
    job = client.post("/v1/jobs", json={"scene_id": scenes["mallory"]}, headers=mallory)
    assert job.status_code == 202, job.text
    job_id = uuid.UUID(job.json()["id"])
    _write_finished_result(Storage(settings.storage).job_dir(job_id), ("wall", "chair", "table"))
    mark_succeeded(settings, job_id)
    vocabulary = next((settings.storage / "scenes" / scenes["alice"]).rglob("vocabulary.json"))
    assert SECRET_CLASSES[0] in vocabulary.read_text()
    return World(
        client=client,
        settings=settings,
        alice=alice,
        mallory=mallory,
        alice_scene=scenes["alice"],
        mallory_scene=scenes["mallory"],
        mallory_job=str(job_id),
        alice_vocabulary=vocabulary,
        valid_members=read_members(write_tiny_bundle(tmp / "bundle-valid")),
        tmp=tmp,
    )


def _pack(folder: Path) -> bytes:
    return pack_members(read_members(folder), "zip")


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Iterator[World]:
    tmp = tmp_path_factory.mktemp("hostile")
    settings = _settings(tmp, "sqlite")
    app = create_app(settings, sender=RecordingSender(), run_reaper=False)
    with TestClient(app, raise_server_exceptions=False) as client:  # a 500 is an answer to check, not a raise
        yield _build_world(client, settings, tmp)
    get_engine.cache_clear()


@pytest.fixture(scope="module", params=["sqlite", "postgres"])
def any_world(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[World]:
    """The module's world, and one on PostgreSQL (for the named cases)."""
    if request.param == "sqlite":
        yield request.getfixturevalue("world")
        return
    from sqlalchemy import text

    url = request.getfixturevalue("pg_url")
    with get_engine(url).begin() as conn:
        conn.execute(text("TRUNCATE artifact, job, scene, upload, api_key CASCADE"))
    tmp = tmp_path_factory.mktemp("hostile-pg")
    settings = _settings(tmp, "postgres", database_url=url)
    with TestClient(
        create_app(settings, sender=RecordingSender(), run_reaper=False), raise_server_exceptions=False
    ) as client:
        yield _build_world(client, settings, tmp)


# -- what every answer must be -------------------------------------------------------------------------------------


def listing(root: Path) -> set[str]:
    """Every file and folder under the storage root, but the top-level folders that hold them."""
    return {p.relative_to(root).as_posix() for p in root.rglob("*")} - {"uploads", "scenes", "artifacts"}


def _rows(world: World, model: Any) -> int:
    with session_scope(get_session_factory(world.settings.database)) as session:
        return int(session.query(model).count())


def assert_safe(
    world: World, response: Response, sent: tuple[str, ...] = (), *, allowed_5xx: tuple[int, ...] = ()
) -> None:
    """Whatever the status: no 5xx (but ``allowed_5xx``), no traceback, no host path, no other tenant's class
    names; an error is JSON with a type and a message."""
    text = response.text
    where = f"{response.request.method} {response.request.url.path} -> {response.status_code}: {text[:600]}"
    assert response.status_code < 500 or response.status_code in allowed_5xx, where
    assert not traceback_markers(text), where
    assert not host_path_leaks(text, known=world.known_paths, sent=sent), where
    assert not [name for name in SECRET_CLASSES if name in text and name not in "".join(sent)], where
    if response.status_code >= 400:
        assert response.headers.get("content-type", "").startswith("application/json"), where
        body = response.json()
        assert isinstance(body.get("type"), str), where
        assert body["type"], where
        assert isinstance(body.get("message"), str), where
        assert body["message"], where


def assert_refused(world: World, response: Response, sent: tuple[str, ...] = (), status: int | None = None) -> None:
    """:func:`assert_safe`, and a 4xx (``status`` when given)."""
    assert_safe(world, response, sent)
    where = f"{response.request.method} {response.request.url.path} -> {response.status_code}: {response.text[:600]}"
    if status is not None:
        assert response.status_code == status, where
    assert 400 <= response.status_code < 500, where


def _post_json(world: World, path: str, body: JsonText | dict[str, Any], auth: dict[str, str]) -> Response:
    if isinstance(body, JsonText):
        return world.client.post(path, content=body.text.encode(), headers={**auth, **JSON_HEADERS})
    return world.client.post(path, json=body, headers=auth)


# -- POST /v1/jobs -----------------------------------------------------------------------------------------------


SCENE = "@SCENE@"  # stands for tenant B's scene id in the templates (the world is made after import)
JOB_TEMPLATES = {
    "scene_id": json.dumps({"scene_id": "@RAW@"}),
    "config": json.dumps({"scene_id": SCENE, "config": "@RAW@"}),
    "config.stage": json.dumps({"scene_id": SCENE, "config": {"language_field": "@RAW@"}}),
    "vocabulary": json.dumps({"scene_id": SCENE, "vocabulary": "@RAW@"}),
    "extra": json.dumps({"scene_id": SCENE, "extra": "@RAW@"}),
}


def _check_job_answer(world: World, response: Response, before: tuple[int, set[str]], sent: tuple[str, ...]) -> None:
    assert_safe(world, response, sent)
    if response.status_code == 202:  # a valid request; the job (never run here) is deleted again
        assert world.client.delete(f"/v1/jobs/{response.json()['id']}", headers=world.mallory).status_code == 204
    assert (_rows(world, Job), listing(world.storage)) == before, response.text[:300]


@BOUNDED
@given(body=hostile_body(JOB_TEMPLATES.__getitem__, list(JOB_TEMPLATES)))
@example(body=JsonText(JOB_TEMPLATES["config.stage"].replace('"@RAW@"', nested_json(300, bracket="{")), "300 deep"))
def test_job_bodies(world: World, body: JsonText) -> None:
    """Hostile config, vocabulary and scene ids: refused with a message, or a plain job; no 5xx."""
    note(f"body: {body!r}")
    before = (_rows(world, Job), listing(world.storage))
    sent = JsonText(body.text.replace(SCENE, world.mallory_scene), body.what)
    response = _post_json(world, "/v1/jobs", sent, world.mallory)
    _check_job_answer(world, response, before, ())


def _path_like(world_paths: list[str]) -> st.SearchStrategy[str]:
    return st.one_of(
        st.sampled_from([*HOST_PATHS, *world_paths]),
        st.builds(
            lambda p, pre, post: pre + p + post,
            st.sampled_from(HOST_PATHS[:4]),
            st.sampled_from(["", " ", "./"]),
            st.sampled_from(["", " ", "/", "/."]),
        ),
    )


@BOUNDED
@given(data=st.data())
def test_a_job_never_names_a_file_of_the_host(world: World, data: st.DataObject) -> None:
    """A vocabulary that is a path (of the host, or of another tenant's vocabulary.json) is refused by the API
    (422): no job exists that a worker would open it for."""
    path = data.draw(_path_like(world.alice_paths), label="vocabulary")
    before = (_rows(world, Job), listing(world.storage))
    response = world.client.post(
        "/v1/jobs", json={"scene_id": world.mallory_scene, "vocabulary": path}, headers=world.mallory
    )
    try:
        assert_refused(world, response, sent=(path,), status=422)
    finally:
        _check_job_answer(world, response, before, (path,))


@pytest.mark.parametrize(
    "body",
    [
        pytest.param(
            lambda w, s: {"scene_id": s, "config": json.loads(nested_json(300, bracket="{"))}, id="config-300-deep"
        ),
        pytest.param(
            lambda w, s: JsonText(f'{{"scene_id": "{s}", "config": {{"a": {nested_json(3000)}}}}}', "3000"),
            id="config-3000-deep",
        ),
        pytest.param(
            lambda w, s: JsonText(f'{{"scene_id": "{s}", "config": {{"a": {huge_integer(5000)}}}}}', "int"),
            id="config-5000-digit-integer",
        ),
    ],
)
def test_deep_or_huge_job_config_is_a_422_naming_the_limit(any_world: World, body: Any) -> None:
    """A config nested hundreds deep or holding a 5000-digit integer: 422 naming the limit."""
    world = any_world
    before = (_rows(world, Job), listing(world.storage))
    response = _post_json(world, "/v1/jobs", body(world, world.mallory_scene), world.mallory)
    if response.status_code == 202:
        world.client.delete(f"/v1/jobs/{response.json()['id']}", headers=world.mallory)
    assert_refused(world, response, status=422)
    text = response.text.lower()
    assert any(word in text for word in ("deep", "depth", "nest", "digit", "integer")), response.text
    assert (_rows(world, Job), listing(world.storage)) == before


@pytest.mark.parametrize("which", ["host", "tenant-absolute", "tenant-relative"])
def test_another_tenants_vocabulary_cannot_be_named(any_world: World, which: str) -> None:
    """The cross-tenant exploit: tenant B names tenant A's vocabulary.json (or /etc/passwd); 422, no job."""
    world = any_world
    path = {"host": "/etc/passwd", "tenant-absolute": world.alice_paths[0], "tenant-relative": world.alice_paths[1]}
    before = _rows(world, Job)
    response = world.client.post(
        "/v1/jobs", json={"scene_id": world.mallory_scene, "vocabulary": path[which]}, headers=world.mallory
    )
    try:
        assert_refused(world, response, sent=(path[which],), status=422)
    finally:
        if response.status_code == 202:
            world.client.delete(f"/v1/jobs/{response.json()['id']}", headers=world.mallory)
    assert _rows(world, Job) == before


# -- POST /v1/jobs/{id}/query ------------------------------------------------------------------------------------


def _query_bodies(world: World) -> st.SearchStrategy[JsonText | dict[str, Any]]:
    templates = {
        "text": json.dumps({"text": "@RAW@"}),
        "vector": json.dumps({"vector": "@RAW@"}),
        "vector[0]": json.dumps({"vector": ["@RAW@", 0, 0, 0, 0, 0, 0, 0]}),
        "top_k": json.dumps({"text": "wall", "top_k": "@RAW@"}),
        "min_score": json.dumps({"vector": [1, 0, 0, 0, 0, 0, 0, 0], "min_score": "@RAW@"}),
    }
    extreme = st.sampled_from([0.0, -0.0, 5e-324, -5e-324, 1e-300, 1e300, -1e308, 1.7976931348623157e308])
    vectors = st.builds(lambda v, k: {"vector": v, "top_k": k}, st.lists(extreme, min_size=1, max_size=FEATURE_DIM + 2),
                        st.integers(1, 1000))  # fmt: skip
    texts = st.builds(lambda t: {"text": t}, st.one_of(st.sampled_from([*SECRET_CLASSES, *world.alice_paths]),
                                                       hostile_json_values()))  # fmt: skip
    return st.one_of(hostile_body(templates.__getitem__, list(templates)), vectors, texts)


@BOUNDED
@given(data=st.data())
def test_query_bodies(world: World, data: st.DataObject) -> None:
    """Hostile queries on B's finished job: ranked hits or a 4xx; never A's classes, never a 5xx."""
    body = data.draw(_query_bodies(world))
    before = listing(world.storage)
    response = _post_json(world, f"/v1/jobs/{world.mallory_job}/query", body, world.mallory)
    assert_safe(world, response, tuple(_strings(body)))  # B may see the names B sent, never A's otherwise
    if response.status_code == 200:
        assert {hit["class_name"] for hit in response.json()["hits"]} <= {"wall", "chair", "table"}
    assert listing(world.storage) == before


def _strings(body: JsonText | dict[str, Any]) -> list[str]:
    if isinstance(body, JsonText):
        return []
    values = [v for v in body.values() if isinstance(v, str)]
    return values


# -- POST /v1/jobs/{id}/render -----------------------------------------------------------------------------------

TINY = st.floats(min_value=5e-324, max_value=1e-6)  # a focal length "near zero"
HUGE = st.floats(min_value=1e12, max_value=1.7976931348623157e308)  # "near the float maximum"
SIGNED_HUGE = st.one_of(HUGE, HUGE.map(lambda v: -v))
RENDER_CAMERA: dict[str, Any] = {"width": 32, "height": 24, "fx": 24.0, "fy": 24.0, "cx": 15.5, "cy": 11.5}


@st.composite
def extreme_renders(draw: st.DrawFn) -> dict[str, Any]:
    """A render request with at least one number far outside any camera's range: a focal length near zero or
    near the float maximum, a principal point or a camera position beyond 1e12."""
    camera = dict(RENDER_CAMERA)
    pose = np.eye(4).tolist()
    which = draw(st.sets(st.sampled_from(["fx", "fy", "cx", "cy", "tx", "tz"]), min_size=1, max_size=3))
    for key in which:
        if key in ("fx", "fy"):
            camera[key] = draw(st.one_of(TINY, HUGE))
        elif key in ("cx", "cy"):
            camera[key] = draw(SIGNED_HUGE)
        else:
            pose["xz".index(key[1]) * 2][3] = draw(SIGNED_HUGE)
    body: dict[str, Any] = {"T_world_cam": pose, "camera": camera, "layer": draw(st.sampled_from(["color", "depth"]))}
    if draw(st.booleans()):
        body["width"], body["height"] = draw(st.sampled_from([(16, 12), (1, 1), (8192, 1)]))
    return body


@FEW
@given(body=extreme_renders())
@example(body={"T_world_cam": np.eye(4).tolist(), "camera": {**RENDER_CAMERA, "cx": 1.7e308}})  # a traceback on main
@example(body={"T_world_cam": np.eye(4).tolist(), "camera": {**RENDER_CAMERA, "fx": 1e-300, "fy": 1e-300}})
def test_render_numbers_are_checked_before_rendering(world: World, body: dict[str, Any]) -> None:
    """Extreme camera and pose numbers: a 422 from the API's own checks, never the render process's traceback
    in a 503."""
    note(f"body: {body!r}")
    before = listing(world.storage)
    response = world.client.post(f"/v1/jobs/{world.mallory_job}/render", json=body, headers=world.mallory)
    assert_refused(world, response, status=422)
    assert listing(world.storage) == before


# -- POST /v1/scenes: request bodies and bad bundles ---------------------------------------------------------------


@BOUNDED
@given(value=hostile_json_values(), slot=st.sampled_from(["upload_id", "name", "extra"]))
def test_scene_bodies(world: World, value: Any, slot: str) -> None:
    """Hostile upload ids (host paths, other tenants' ids, wrong types) and names: a 4xx, nothing made."""
    note(f"{slot} = {value!r}")
    body: dict[str, Any] = {"upload_id": str(uuid.uuid4()), slot: value}
    before = (_rows(world, Upload), listing(world.storage), _scene_count(world))
    response = world.client.post("/v1/scenes", json=body, headers=world.mallory)
    assert_refused(world, response, sent=tuple(s for s in [value] if isinstance(s, str)))
    assert (_rows(world, Upload), listing(world.storage), _scene_count(world)) == before


def test_another_tenants_upload_cannot_become_a_scene(world: World) -> None:
    upload = upload_bytes(world.client, world.alice, b"PK\x05\x06" + bytes(18), filename="a.zip")
    before = listing(world.storage)
    response = world.client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=world.mallory)
    assert_refused(world, response, status=404)
    assert listing(world.storage) == before
    assert world.client.delete(f"/v1/uploads/{upload['id']}", headers=world.alice).status_code == 204


def _scene_count(world: World) -> int:
    return int(world.client.get("/v1/scenes", headers=world.mallory).json()["count"])


def _refused_bundle(world: World, bad: BadBundle, *, may_pass: bool = False) -> Response:
    """Upload ``bad`` as tenant B and make a scene of it; assert a clean refusal (or, with ``may_pass``, a scene
    that is deleted again) and that the storage is as before."""
    before = listing(world.storage)
    scenes = _scene_count(world)
    upload = upload_bytes(world.client, world.mallory, bad.data, filename="bad.zip")
    response = world.client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=world.mallory)
    where = f"{bad.what} -> {response.status_code}: {response.text[:800]}"
    if may_pass and response.status_code == 201:  # the "damage" left a valid bundle
        scene = response.json()["id"]
        assert world.client.delete(f"/v1/scenes/{scene}", headers=world.mallory).status_code == 204
    else:
        assert_refused(world, response, sent=bad.echoes)
        if bad.file is not None:
            assert bad.file in response.text, f"the refusal does not name {bad.file}: {where}"
        assert world.client.get(f"/v1/uploads/{upload['id']}", headers=world.mallory).status_code == 404, where
    assert _scene_count(world) == scenes, where
    assert listing(world.storage) == before, f"files left behind: {listing(world.storage) ^ before}; {where}"
    return response


@hypothesis_settings(BOUNDED, max_examples=30)
@given(damage=damages())
def test_bad_bundles(world: World, damage: Damage) -> None:
    """Generated bad bundles (deep or huge JSON, wrong types, missing files, unsafe or overlong member names,
    links, images whose headers declare huge sizes, PLY and .npy headers with absurd counts), as zip, tar and
    tar.gz: a 422 naming the file, nothing kept."""
    note(f"damage: {damage!r}")
    bad = damage.apply(world.valid_members)
    _refused_bundle(world, bad, may_pass=_may_leave_a_valid_bundle(damage))


def _may_leave_a_valid_bundle(damage: Damage) -> bool:
    """A wrong type or a plain raw value may happen to be valid where it lands (a string name, a float pose
    entry); deep nesting and integers beyond a float never are."""
    if isinstance(damage, WrongType):
        return True
    if isinstance(damage, RawField):
        if damage.label.startswith("nested"):
            return False
        digits = damage.raw.lstrip("-")
        return not (digits.isdigit() and len(digits) > 308)
    return False


@given(damage=damages(link_targets=["../../../scenes"]))
@hypothesis_settings(FEW)
def test_bundle_links_never_reach_other_files(world: World, damage: Damage) -> None:
    """Links to the host and into the storage (other tenants' scenes) are refused like every other damage."""
    note(f"damage: {damage!r}")
    if not (isinstance(damage, ExtraMember) and damage.link is not None):
        damage = ExtraMember(name="passwd", link=Link(str(world.alice_vocabulary)), kind=damage.kind)
    _refused_bundle(world, damage.apply(world.valid_members))


NAMED_BUNDLES = [
    pytest.param(WholeFile(file="scene.json", content=nested_json(100_000).encode(), label="100000 deep"),
                 id="scene-json-100000-deep"),
    pytest.param(RawField(file="scene.json", path=("name",), raw=nested_json(5000, bracket="{"), label="5000 deep"),
                 id="scene-json-field-5000-deep"),
    pytest.param(WholeFile(file="vocabulary.json", content=nested_json(50_000, bracket="{").encode(), label="deep"),
                 id="vocabulary-json-50000-deep"),
    pytest.param(RawField(file="scene.json", path=("camera", "width"), raw=huge_integer(5000), label="5000 digits"),
                 id="scene-json-5000-digit-integer"),
    pytest.param(RawField(file="vocabulary.json", path=("classes", 0, "kind"), raw=huge_integer(10_000),
                          label="10000 digits"), id="vocabulary-json-10000-digit-integer"),
    pytest.param(WholeFile(file="geometry.ply", content=b"ply\nformat ascii 1.0\nelement vertex " + huge_integer(5000)
                           .encode() + b"\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
                           label="5000-digit vertex count"), id="ply-5000-digit-vertex-count"),
    pytest.param(WholeFile(file="features/000000.npy", content=npy_header((10**30, 6, 8)), label="shape 1e30"),
                 id="npy-shape-1e30"),
    pytest.param(WholeFile(file="features/000000.npy", content=npy_header((10**19, 6, 8)), label="shape 1e19"),
                 id="npy-shape-1e19-no-data"),  # 10**19 * 6 * 8 wraps to 0 in int64: "complete" without data
    pytest.param(Image(file="color/000001.jpg", width=40_000, height=40_000, color_type=2),
                 id="color-png-header-40000-by-40000"),
    pytest.param(ExtraMember(name="color/" + "n" * 300 + ".png"), id="member-name-300-chars"),
    pytest.param(ExtraMember(name="d/" * 2100 + "f.bin", kind="tar"), id="member-path-4200-chars"),
    pytest.param(Image(file="masks/000000.png", width=2**31 - 1, height=2**31 - 1), id="mask-png-header-2g-by-2g"),
    pytest.param(Image(file="depth/000000.png", width=40_000, height=40_000, bit_depth=16),
                 id="depth-png-header-40000-by-40000"),
]  # fmt: skip


@pytest.mark.parametrize("damage", NAMED_BUNDLES)
def test_named_bad_bundles(world: World, damage: Damage) -> None:
    """The named bad bundles: each a 422 that names the file (relative to the bundle), nothing kept. (Validation
    does not touch the database: one backend is enough.)"""
    _refused_bundle(world, damage.apply(world.valid_members))


def test_a_huge_mask_is_refused_from_its_header(world: World) -> None:
    """A 20000 x 20000 mask in a small bundle (an image bomb): a 422 naming the file, not an accepted scene.
    (An 8-bit one: 400 MB decoded where the header is not read first.)"""
    bad = Image(file="masks/000000.png", width=20_000, height=20_000, complete=True).apply(world.valid_members)
    assert len(bad.data) < 2_000_000
    _refused_bundle(world, bad)


def test_image_headers_are_checked_before_decoding(world: World) -> None:
    """A depth map of 6000 x 6000 (16-bit, valid, 72 MB decoded) against a 64 x 48 camera: refused from its
    header, so the API never holds the decoded image. tracemalloc sees numpy and OpenCV's arrays."""
    bad = Image(file="depth/000000.png", width=6000, height=6000, bit_depth=16, complete=True)
    data = bad.apply(world.valid_members)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        _refused_bundle(world, data)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 40_000_000, f"{peak:,} bytes allocated while refusing a 72 MB image: it was decoded"


def test_a_frame_path_naming_the_host_is_refused(world: World, tmp_path: Path) -> None:
    """scene.json naming /etc/passwd or another tenant's files as a frame's colour image: refused, never read."""
    for i, target in enumerate(["/etc/passwd", str(world.alice_vocabulary), "../../" + world.alice_paths[1]]):

        def point_color_at(root: Path, target: str = target) -> None:
            edit_manifest(root, lambda m: m["frames"][0].__setitem__("color", target))

        folder = write_tiny_bundle(tmp_path / f"b{i}", mutate=point_color_at)
        bad = BadBundle(pack_members(read_members(folder), "zip"), f"frames[0].color = {target}", echoes=(target,))
        _refused_bundle(world, bad)


# -- /v1/uploads: headers ------------------------------------------------------------------------------------------


def _b64(text: str) -> str:
    return base64.b64encode(text.encode()).decode()


def _metadata_values(header: str | None) -> list[str]:
    """The decoded values of an Upload-Metadata header (the client's own filename may be echoed)."""
    values = []
    for pair in (header or "").split(","):
        parts = pair.strip().split(" ")
        try:
            values.append(base64.b64decode(parts[1], validate=True).decode() if len(parts) == 2 else "")
        except ValueError:
            continue
    return values


def _metadata() -> st.SearchStrategy[str]:
    pairs = st.one_of(
        st.builds(
            lambda v: f"filename {_b64(v)}", st.sampled_from([*HOST_PATHS, "../../../x.zip", "a" * 5000, "\x00"])
        ),
        st.builds(lambda v: f"sha256 {_b64(v)}", st.sampled_from(["0" * 63, "z" * 64, "", "0" * 64 + "0"])),
        header_values(),
    )
    return st.lists(pairs, min_size=1, max_size=3).map(",".join)


@BOUNDED
@given(
    length=header_values(),
    metadata=st.none() | _metadata(),
    checksum=st.none() | header_values(),
    version=st.sampled_from([None, "1.0.0", "0.2.2", ""]),
    body=st.sampled_from([b"", b"x" * 10, b"PK\x03\x04"]),
)
def test_upload_creation_headers(
    world: World, length: str, metadata: str | None, checksum: str | None, version: str | None, body: bytes
) -> None:
    """Hostile Upload-Length, Upload-Metadata, Upload-Checksum, Tus-Resumable: an upload or a 4xx; after a
    refusal no upload row and no file."""
    note(f"headers: {length=} {metadata=} {checksum=} {version=} {body=}")
    headers = {**world.mallory, "Upload-Length": length}
    for name, value in (("Upload-Metadata", metadata), ("Upload-Checksum", checksum), ("Tus-Resumable", version)):
        if value is not None:
            headers[name] = value
    if body:
        headers["Content-Type"] = OCTET
    before = (_rows(world, Upload), listing(world.storage))
    response = world.client.post("/v1/uploads", content=body, headers=headers)
    sent = tuple(v for v in (length, metadata, checksum, version, *_metadata_values(metadata)) if v)
    assert_safe(world, response, sent, allowed_5xx=(507,))  # 507: the disk cannot hold the declared length
    if response.status_code == 201:
        ident = response.json()["id"]
        assert world.client.delete(f"/v1/uploads/{ident}", headers=world.mallory).status_code == 204
    assert (_rows(world, Upload), listing(world.storage)) == before, response.text[:300]


@BOUNDED
@given(
    offset=header_values() | st.just("0"),
    checksum=st.none() | header_values(),
    content_type=st.sampled_from([OCTET, "application/json", "text/plain", ""]),
    body=st.sampled_from([b"", b"0123456789", b"0123456789ABCDEF"]),
)
def test_upload_patch_headers(world: World, offset: str, checksum: str | None, content_type: str, body: bytes) -> None:
    """Hostile PATCHes on a 10-byte upload: 204 or a 4xx; the upload's offset never passes what arrived."""
    note(f"headers: {offset=} {checksum=} {content_type=} {body=}")
    created = world.client.post("/v1/uploads", headers={**world.mallory, "Upload-Length": "10"})
    assert created.status_code == 201, created.text
    ident = created.json()["id"]
    before = listing(world.storage)
    headers = {**world.mallory, "Upload-Offset": offset, "Tus-Resumable": "1.0.0"}
    if content_type:
        headers["Content-Type"] = content_type
    if checksum is not None:
        headers["Upload-Checksum"] = checksum
    response = world.client.patch(f"/v1/uploads/{ident}", content=body, headers=headers)
    assert_safe(world, response, tuple(v for v in (offset, checksum) if v), allowed_5xx=(507,))
    state = world.client.get(f"/v1/uploads/{ident}", headers=world.mallory)
    if state.status_code == 200:  # a whole-file checksum mismatch discards the upload (404)
        assert 0 <= state.json()["offset"] <= 10
        if response.status_code >= 400:
            assert state.json()["offset"] == 0, state.text
    if response.status_code >= 400:
        assert listing(world.storage) <= before, listing(world.storage) ^ before
    world.client.delete(f"/v1/uploads/{ident}", headers=world.mallory)


@pytest.mark.parametrize("step", ["create", "create-with-body", "patch"])
def test_uploads_check_the_free_disk(tmp_path: Path, step: str) -> None:
    """An upload the free disk cannot hold (PANOGS_MIN_FREE_DISK_BYTES above the free space) is refused at once
    with 507 (or 413) and the reason, before any byte is stored; a PATCH checks again."""
    data = b"PK\x05\x06" + bytes(18)
    settings = _settings(tmp_path, "sqlite", min_free_disk_bytes=2**62, quota_bytes=None)
    key = new_key(settings, "mallory")
    made = _upload_made_with_room(tmp_path, key, len(data)) if step == "patch" else None  # before the disk filled
    with TestClient(
        create_app(settings, sender=RecordingSender(), run_reaper=False), raise_server_exceptions=False
    ) as client:
        world = World(client, settings, key, key, "", "", "", tmp_path, {}, tmp_path)
        before = (_rows(world, Upload), listing(settings.storage))
        tus = {**key, "Tus-Resumable": "1.0.0"}
        if step == "create":
            response = client.post("/v1/uploads", headers={**tus, "Upload-Length": str(len(data))})
        elif step == "create-with-body":
            headers = {**tus, "Upload-Length": str(len(data)), "Content-Type": OCTET}
            response = client.post("/v1/uploads", content=data, headers=headers)
        else:
            headers = {**tus, "Upload-Offset": "0", "Content-Type": OCTET}
            response = client.patch(f"/v1/uploads/{made}", content=data, headers=headers)
        assert response.status_code in (507, 413), response.text
        assert_safe(world, response, allowed_5xx=(507,))
        assert "disk" in response.text.lower(), response.text
        assert (_rows(world, Upload), listing(settings.storage)) == before
        assert not any(p.stat().st_size for p in settings.storage.rglob("*") if p.is_file())


def _upload_made_with_room(tmp_path: Path, key: dict[str, str], length: int) -> str:
    """An empty upload of ``length`` bytes made by an app with no free-disk reserve (same database, storage)."""
    settings = _settings(tmp_path, "sqlite", min_free_disk_bytes=0, quota_bytes=None)
    with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
        response = client.post("/v1/uploads", headers={**key, "Upload-Length": str(length)})
        assert response.status_code == 201, response.text
        return str(response.json()["id"])


# -- names in paths ----------------------------------------------------------------------------------------------

# Percent-encoded: a client (httpx as well) resolves a literal ".." segment before sending.
TRAVERSALS = ["%2e%2e", "..%2fscene.json", "%2e%2e%2f%2e%2e%2fetc%2fpasswd", "..%5c..%5cpasswd", "%00", ".env",
              "gaussians.ply%00.txt", "instances.json%2f..%2f..%2fpanogs.db"]  # fmt: skip


@pytest.mark.parametrize("name", TRAVERSALS)
def test_names_in_paths_never_leave_their_folder(world: World, name: str) -> None:
    """An artifact or app asset named with a traversal (raw or percent-encoded): a 404 or another 4xx, and
    never the bytes of a file outside the job's artifacts or the app's assets."""
    for url in (f"/v1/jobs/{world.mallory_job}/artifacts/{name}", f"/app/static/{name}"):
        response = world.client.get(url, headers=world.mallory)
        assert_refused(world, response, sent=(name,))
        assert b"root:" not in response.content
        assert b"SQLite format" not in response.content


# -- text that a database may refuse -------------------------------------------------------------------------------


@pytest.mark.parametrize("field", ["job-vocabulary", "scene-name", "upload-filename", "upload-filename-with-body"])
def test_nul_characters_in_stored_text(any_world: World, field: str) -> None:
    """U+0000 in a text the service stores (PostgreSQL refuses it in text columns): accepted or a 4xx, never a
    500, and nothing left behind either way. (Found by this suite, not reported before.)"""
    world = any_world
    client, auth = world.client, world.mallory
    nul = "chair\x00/etc/passwd"
    if field.startswith("upload-filename"):
        metadata = f"filename {_b64(nul)}"
        before = (_rows(world, Upload), listing(world.storage))
        headers = {**auth, "Tus-Resumable": "1.0.0", "Upload-Length": "10", "Upload-Metadata": metadata}
        body = b""
        if field.endswith("with-body"):
            headers["Content-Type"], body = OCTET, b"0123456789"
        response = client.post("/v1/uploads", content=body, headers=headers)
        assert_safe(world, response, (nul, metadata))
        if response.status_code == 201:
            assert client.delete(f"/v1/uploads/{response.json()['id']}", headers=auth).status_code == 204
        assert (_rows(world, Upload), listing(world.storage)) == before
    elif field == "scene-name":
        bad = BadBundle(pack_members(world.valid_members, "zip"), "a valid bundle, a NUL in its name")
        stored, scenes = listing(world.storage), _scene_count(world)
        upload = upload_bytes(client, auth, bad.data, filename="ok.zip")
        response = client.post("/v1/scenes", json={"upload_id": upload["id"], "name": nul}, headers=auth)
        assert_safe(world, response, (nul,))
        if response.status_code == 201:
            assert client.delete(f"/v1/scenes/{response.json()['id']}", headers=auth).status_code == 204
        else:
            client.delete(f"/v1/uploads/{upload['id']}", headers=auth)
        assert (listing(world.storage), _scene_count(world)) == (stored, scenes)
    else:
        before_jobs = _rows(world, Job)
        response = client.post("/v1/jobs", json={"scene_id": world.mallory_scene, "vocabulary": nul}, headers=auth)
        if response.status_code == 202:
            client.delete(f"/v1/jobs/{response.json()['id']}", headers=auth)
        assert_safe(world, response, (nul,))
        assert _rows(world, Job) == before_jobs


# -- /app/session and the headers of every answer ---------------------------------------------------------------------


@BOUNDED
@given(data=st.data())
def test_app_session_bodies(world: World, data: st.DataObject) -> None:
    """Hostile sign-in bodies (deep, huge, NUL, paths, another tenant's key shape): 401 or another 4xx, no
    cookie, no 5xx."""
    body = data.draw(
        st.one_of(
            hostile_body(lambda _slot: json.dumps({"key": "@RAW@"}), ["key"]),
            st.builds(lambda v: {"key": v}, hostile_json_values(["pgs_", "pgs_" + "A" * 43, "Bearer pgs_x"])),
        )
    )
    response = _post_json(world, "/app/session", body, {})
    assert_refused(world, response, sent=tuple(_strings(body)))
    assert "set-cookie" not in response.headers


SECURITY_HEADERS = ("x-content-type-options", "referrer-policy")


@pytest.mark.parametrize(
    ("method", "path", "body"),
    [
        ("GET", "/app", None),
        ("POST", "/app/session", {"key": "pgs_wrong"}),
        ("POST", "/app/session", {"key": json.loads(nested_json(50))}),
        ("GET", "/v1/jobs", None),
        ("POST", "/v1/jobs", {"scene_id": "x"}),
        ("GET", "/healthz", None),
    ],
)
def test_every_answer_forbids_framing_and_sniffing(world: World, method: str, path: str, body: Any) -> None:
    """Answers, refusals included, carry a strict set of security headers."""
    response = world.client.request(method, path, json=body)
    headers = {k.lower(): v for k, v in response.headers.items()}
    assert headers.get("x-content-type-options") == "nosniff", headers
    assert "referrer-policy" in headers, headers
    framing = headers.get("x-frame-options", "").upper() in ("DENY", "SAMEORIGIN") or "frame-ancestors" in headers.get(
        "content-security-policy", ""
    )
    assert framing, headers
