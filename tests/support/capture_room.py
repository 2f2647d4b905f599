"""A synthetic room written in the layouts of real capture tools, and the checks the importer tests share.

Each writer exports a bundle (``panogs synth``'s tiny room) with the format's own axes, units, file names and
quirks, so that an importer that forgets one (OpenGL axes, EXR metres, depth / 5000, column-major K) fails the
pose, intrinsics or point checks below.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from panogs_core.io.bundle import open_bundle
from panogs_core.io.bundle.reader import Bundle
from panogs_core.types import Camera

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # written here on purpose, not imported from the code under test


def quaternion_xyzw(R: np.ndarray) -> np.ndarray:  # (4,) scalar-last unit quaternion of a rotation
    """Shepperd's method, written independently of the importers' quaternion -> matrix code."""
    m = R
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def export_maps(scene: Bundle, stems: list[str], dst: Path) -> tuple[Path, Path]:
    """The room's feature maps and masks as the folders a user would pass (``<stem>.npy``, ``<stem>.png``)."""
    (dst / "features").mkdir(parents=True)
    (dst / "masks").mkdir()
    for frame, stem in zip(scene.frames, stems):
        if frame.features is not None:
            np.save(dst / "features" / f"{stem}.npy", np.asarray(scene.read_features(frame)))
        if frame.masks is not None:
            cv2.imwrite(str(dst / "masks" / f"{stem}.png"), scene.read_masks(frame).astype(np.uint16))
    return dst / "features", dst / "masks"


def tilted_world(axis: tuple[float, float, float], degrees: float) -> np.ndarray:  # (4, 4)
    """A rigid transform turning the room's world by ``degrees`` about ``axis`` (Rodrigues), for a capture written
    in a world whose up is not the room's z: the room's up becomes ``tilted_world(...)[:3, 2]``."""
    k = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = np.radians(degrees)
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
    return T


# The tilted world of the up-direction tests (tests/conftest.py's tilted_tum_run): the room's z-up ends up 55
# degrees from every world axis it had.
TILTED_55 = tilted_world((1.0, 0.4, 0.0), 55.0)


def write_tum(
    room: Path, dst: Path, *, jitter: float = 0.007, world: np.ndarray | None = None, decimals: int = 9
) -> list[float]:
    """The room as a TUM RGB-D sequence: depth * 5000, timestamps of the streams off by ``jitter`` seconds; the
    poses in ``world`` (a (4, 4) applied to the room's world; ``tilted_world``) when given; the ground truth's numbers
    with ``decimals`` decimals (the benchmark's own files have 4).

    Returns the depth timestamps, one per room frame. The ground truth has a row near each frame (off by
    ``jitter / 2``) and rows between frames with other poses, so only the nearest-in-time row is right.
    """
    scene = open_bundle(room)
    (dst / "rgb").mkdir(parents=True)
    (dst / "depth").mkdir()
    rgb_lines, depth_lines, gt_lines, stamps = ["# color images"], ["# depth maps"], ["# ground truth"], []
    for i, frame in enumerate(scene.frames):
        t = 1305031102.0 + i / 30.0
        stamps.append(t)
        depth = np.round(scene.read_depth(frame).astype(np.float64) * 5000.0).astype(np.uint16)
        cv2.imwrite(str(dst / "depth" / f"{t:.6f}.png"), depth)
        rgb = scene.read_color(frame)
        cv2.imwrite(str(dst / "rgb" / f"{t + jitter:.6f}.png"), rgb[:, :, ::-1])
        depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
        rgb_lines.append(f"{t + jitter:.6f} rgb/{t + jitter:.6f}.png")
        T = (np.eye(4) if world is None else world) @ np.asarray(frame.T_world_cam)
        q = quaternion_xyzw(T[:3, :3])
        gt_lines.append(f"{t + jitter / 2:.4f} " + " ".join(f"{v:.{decimals}f}" for v in (*T[:3, 3], *q)))
        gt_lines.append(f"{t + 1 / 60:.4f} 9 9 9 0 0 0 1")  # between frames: a pose no frame may take
    (dst / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (dst / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (dst / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    return stamps


def import_tilted_tum(room: Path, root: Path, world: np.ndarray, *, stride: int = 2) -> Path:
    """The room written as a TUM sequence (which records no gravity) in ``world`` and imported back with the
    room's maps and vocabulary, every ``stride``-th frame kept; returns the bundle folder (``root / "bundle"``)."""
    from panogs_core.io.importers.capture import FrameSelection, MapSources
    from panogs_core.io.importers.tum import TumOptions, import_tum

    scene = open_bundle(room)
    stamps = write_tum(room, root / "seq", world=world)
    cam = scene.camera
    (root / "seq" / "intrinsics.txt").write_text(f"{cam.fx!r} {cam.fy!r} {cam.cx!r} {cam.cy!r}\n")
    features, masks = export_maps(scene, [f"{t:.6f}" for t in stamps], root / "maps")
    maps = MapSources(features=features, masks=masks, feature_space=scene.feature_space, vocabulary=scene.vocabulary)
    selection = FrameSelection(stride=stride)
    import_tum(root / "seq", root / "bundle", TumOptions(intrinsics=root / "seq" / "intrinsics.txt", maps=maps,
                                                         selection=selection))  # fmt: skip
    return root / "bundle"


def write_record3d(room: Path, dst: Path, *, color_scale: int = 4, world: np.ndarray | None = None) -> None:
    """The room as a Record3D EXR + JPG export: colour ``color_scale`` times the depth size, K column-major at
    the colour size, ARKit (OpenGL-axes) quaternion poses, EXR depth in metres, confidence all high; the poses in
    ``world`` (a (4, 4) applied to the room's world) when given (ARKit's own world is +Y up)."""
    import OpenEXR

    scene = open_bundle(room)
    cam = scene.camera
    big = cam.scaled(cam.width * color_scale, cam.height * color_scale)
    for sub in ("rgb", "depth", "conf"):
        (dst / sub).mkdir(parents=True, exist_ok=True)
    poses = []
    for n, frame in enumerate(scene.frames):
        depth = scene.read_depth(frame).astype(np.float32)
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        OpenEXR.File(header, {"R": depth}).write(str(dst / "depth" / f"{n}.exr"))
        rgb = cv2.resize(scene.read_color(frame), (big.width, big.height), interpolation=cv2.INTER_LINEAR)
        cv2.imwrite(str(dst / "rgb" / f"{n}.jpg"), rgb[:, :, ::-1])
        cv2.imwrite(str(dst / "conf" / f"{n}.png"), np.full(depth.shape, 2, np.uint8))
        T_gl = (np.eye(4) if world is None else world) @ np.asarray(frame.T_world_cam) @ GL_TO_CV
        poses.append([*quaternion_xyzw(T_gl[:3, :3]).tolist(), *T_gl[:3, 3].tolist()])
    K = big.K.T.reshape(-1).tolist()  # column-major
    meta = {"K": K, "w": big.width, "h": big.height, "fps": 60, "poses": poses}
    (dst / "metadata.json").write_text(json.dumps(meta))


def write_nerfstudio(room: Path, dst: Path, *, color_scale: int = 2) -> dict[str, object]:
    """The room as an ns-process-data folder: OpenGL ``transform_matrix``, intrinsics at the colour size on the
    top level, millimetre depth PNGs at the depth size. Returns the ``transforms.json`` document."""
    scene = open_bundle(room)
    cam = scene.camera
    big = cam.scaled(cam.width * color_scale, cam.height * color_scale)
    (dst / "images").mkdir(parents=True)
    (dst / "depth").mkdir()
    frames = []
    for n, frame in enumerate(scene.frames):
        name = f"frame_{n + 1:05d}.png"
        rgb = cv2.resize(scene.read_color(frame), (big.width, big.height), interpolation=cv2.INTER_LINEAR)
        cv2.imwrite(str(dst / "images" / name), rgb[:, :, ::-1])
        depth_mm = np.round(scene.read_depth(frame).astype(np.float64) * 1000.0).astype(np.uint16)
        cv2.imwrite(str(dst / "depth" / name), depth_mm)
        T_gl = np.asarray(frame.T_world_cam) @ GL_TO_CV
        frames.append(
            {"file_path": f"images/{name}", "depth_file_path": f"depth/{name}", "transform_matrix": T_gl.tolist()}
        )
    doc: dict[str, object] = {
        "camera_model": "OPENCV",
        "fl_x": big.fx,
        "fl_y": big.fy,
        "cx": big.cx,
        "cy": big.cy,
        "w": big.width,
        "h": big.height,
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "frames": frames,
    }
    (dst / "transforms.json").write_text(json.dumps(doc))
    return doc


def assert_same_cameras(imported: Bundle, room: Bundle, pairs: list[tuple[str, str]], tol: float = 1e-5) -> None:
    """Every imported pose equals the room's (``(imported id, room id)`` pairs), and the cameras agree."""
    a, b = imported.camera, room.camera
    assert (a.width, a.height) == (b.width, b.height)
    assert np.allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], atol=1e-6 * a.fx)
    by_id = {f.id: f for f in imported.frames}
    room_by_id = {f.id: f for f in room.frames}
    for got, want in pairs:
        assert np.allclose(by_id[got].T_world_cam, room_by_id[want].T_world_cam, atol=tol), (got, want)


def world_point(scene: Bundle, frame_id: str, u: int, v: int) -> np.ndarray:  # (3,) world, metres
    frame = next(f for f in scene.frames if f.id == frame_id)
    z = float(scene.read_depth(frame)[v, u])
    cam: Camera = scene.camera
    x_cam = np.array([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z, 1.0])
    return (np.asarray(frame.T_world_cam) @ x_cam)[:3]


def assert_points_agree(imported: Bundle, room: Bundle, pairs: list[tuple[str, str]], tol: float = 0.01) -> None:
    """A pixel of the first frame lands where the room puts it, and where a second frame sees the same point."""
    first, room_first = pairs[0]
    cam = imported.camera
    depth = imported.read_depth(next(f for f in imported.frames if f.id == first))
    v, u = np.argwhere(depth > 0)[len(np.argwhere(depth > 0)) // 2]
    point = world_point(imported, first, int(u), int(v))
    assert np.allclose(point, world_point(room, room_first, int(u), int(v)), atol=tol)
    seen = 0
    for got, _ in pairs[1:]:
        frame = next(f for f in imported.frames if f.id == got)
        x = np.linalg.inv(np.asarray(frame.T_world_cam)) @ np.append(point, 1.0)
        if x[2] <= 0.1:
            continue
        u2, v2 = round(cam.fx * x[0] / x[2] + cam.cx), round(cam.fy * x[1] / x[2] + cam.cy)
        if not (0 <= u2 < cam.width and 0 <= v2 < cam.height):
            continue
        z = float(imported.read_depth(frame)[v2, u2])
        if abs(z - x[2]) > 0.05:  # occluded or at an edge there
            continue
        assert np.linalg.norm(world_point(imported, got, u2, v2) - point) < 0.05 + 0.02 * z
        seen += 1
    assert seen >= 1, "no second frame sees the point"


def pack_r3d(export: Path, archive: Path) -> None:
    """An EXR + JPG export (``write_record3d``) repacked as a ``.r3d`` archive: LZFSE float32 depth and uint8
    confidence under ``rgbd/``, ``metadata`` with the depth size."""
    import zipfile

    import liblzfse

    from panogs_core.io.importers.record3d import read_exr_depth

    meta = json.loads((export / "metadata.json").read_text())
    with zipfile.ZipFile(archive, "w") as zf:
        for exr in sorted((export / "depth").glob("*.exr")):
            n = exr.stem
            depth = read_exr_depth(exr)
            meta["dh"], meta["dw"] = depth.shape
            zf.writestr(f"rgbd/{n}.depth", liblzfse.compress(depth.astype(np.float32).tobytes()))
            conf = cv2.imread(str(export / "conf" / f"{n}.png"), cv2.IMREAD_UNCHANGED).astype(np.uint8)
            zf.writestr(f"rgbd/{n}.conf", liblzfse.compress(conf.tobytes()))
            zf.write(export / "rgb" / f"{n}.jpg", f"rgbd/{n}.jpg")
        zf.writestr("metadata", json.dumps(meta))
