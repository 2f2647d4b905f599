"""The Gaussian scene: fit quality on held-out frames, and the cost of the CPU rasteriser and fit.

Usage:
    python bench/gaussians.py photometric [--sevenscenes DIR] [--stride 10] [--schedules zero cpu gpu]
        [--eval-width 320] [--renders DIR] [--json FILE]
    python bench/gaussians.py quality [--work bench/results/gaussians] [--threads 1] [--json FILE]
    python bench/gaussians.py cost [--threads 1] [--iterations 5] [--json FILE]
    python bench/gaussians.py stage [--threads 1] [--preset small]  # the stage's wall time, default schedule
    python bench/gaussians.py tiles [--sevenscenes DIR] [--widths 80 160] [--iterations 12]

photometric: held-out views (every 8th colour frame left out of the fit) of a real capture and of the synthetic
rooms, side by side: PSNR and SSIM at zero iterations (the initialisation), after the CPU default and after the GPU
schedule (only where torch sees CUDA; otherwise the row says "not run"), each case in its own child process with
the fit's wall time and the process's peak RSS (and CUDA peak). All renders are scored at ``--eval-width`` (the
camera scaled, 320 x 240 by default) whatever the fit's width, so that the schedules compare. The real capture is
a 7-Scenes sequence (``--sevenscenes``, e.g. tsdf-fusion-python's ``data/``; never in this repository, its licence
is non-commercial) imported with ``--stride`` and placeholder feature maps (docs/gaussians.md). ``--renders``
writes, per scene and case, the first held-out frame's render beside its colour frame.

quality: for each scene, the primitives' initialisation and the fitted scene (default CPU schedule, every 8th
colour frame held out of the fit) are rendered at the fit resolution on the held-out frames; PSNR and SSIM are
the means over those frames. Scenes: the small default synthetic room (seeds 0 and 1, geometry path) and the
ScanNet-like round trip (bench/scannet_like.py: the tiny room exported as ScanNet, imported, TSDF primitives).

cost: seconds per iteration (forward + backward + Adam step of the fit, and a forward-only render) and peak RSS
for 30k and 150k Gaussians at 160x120 and 320x240, each case in its own child process so that its peak RSS is
its own; and one 640x480 render of 150k Gaussians. The 30k scene is the small room's primitives; the 150k one is
five copies of them jittered by 1 cm (scales recomputed from the denser neighbours), the same room at 5x density.

tiles: CPU seconds of one training step (render, loss, backward) at each width for several (tile size, tiles per
batch, chunk) settings of the torch rasteriser, twice over, interleaved; on the 7-Scenes bundle when given, else on
the small synthetic room. The training step's settings (``backends.TRAINING_TILES``) come from it.

Timings are wall and CPU seconds of this process; the machine may be shared (the docs say when it was).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from panogs_core.gaussians import AppearanceConfig, fit_appearance  # noqa: E402
from panogs_core.io.bundle import Bundle, open_bundle  # noqa: E402
from panogs_core.stages.primitives import PrimitivesConfig, build_primitives, gaussian_log_scales  # noqa: E402
from panogs_core.synthetic import make_scene  # noqa: E402

WORK = ROOT / "bench" / "results" / "gaussians"
HELD_OUT_EVERY = 8


def _rooms(work: Path) -> dict[str, Path]:
    """The bundles of the quality table (generated once, reused)."""
    rooms = {}
    for seed in (0, 1):
        path = work / f"small-default-{seed}"
        if not (path / "scene.json").is_file():
            make_scene(path, preset="small", difficulty="default", seed=seed)
        rooms[f"synthetic small default seed {seed}"] = path
    rooms["ScanNet-like round trip (tiny, TSDF)"] = _scannet_like(work)
    return rooms


def _scannet_like(work: Path) -> Path:
    sys.path.insert(0, str(ROOT / "bench"))
    from scannet_like import write_scannet_export

    bundle = work / "scannet-like" / "bundle"
    if (bundle / "scene.json").is_file():
        return bundle
    root = work / "scannet-like"
    if root.exists():
        shutil.rmtree(root)
    synthetic = make_scene(
        root / "synthetic",
        preset="tiny",
        difficulty="default",
        seed=0,
        feature_space="clip-vit-b32",
        with_geometry=False,
    )
    export = write_scannet_export(synthetic, root / "scans" / "scene0000_00", seed=0)
    argv = [sys.executable, "-m", "panogs_core.cli", "import", "scannet", str(export.root), str(bundle)]
    argv += ["--vocabulary", str(synthetic / "vocabulary.json")]
    subprocess.run(argv, check=True, cwd=ROOT, capture_output=True)
    return bundle


def _initial_colors(scene: Bundle, prims: Any) -> np.ndarray:
    """The colours export would write without the fit: the geometry's, else fused from the frames, else grey."""
    if prims.colors is not None:
        return np.asarray(prims.colors, np.float32)
    from panogs_core.pipeline.config import PipelineConfig
    from panogs_core.pipeline.stage_table import fusion, visibility
    from panogs_core.stages.export import primitive_colors

    cfg = PipelineConfig()
    vis = visibility(scene, prims, cfg, lambda d, t: None)
    return primitive_colors(prims, fusion(scene, vis, prims, cfg, lambda d, t: None))


def quality(work: Path) -> list[dict[str, Any]]:
    rows = []
    for name, bundle in _rooms(work).items():
        scene = open_bundle(bundle)
        prims = build_primitives(scene, PrimitivesConfig())
        colors = _initial_colors(scene, prims)
        t0, c0 = time.perf_counter(), time.process_time()
        cfg = AppearanceConfig(held_out_every=HELD_OUT_EVERY, cpu_threads=None)  # --threads decides
        fitted = fit_appearance(scene, prims, colors, cfg)
        row = {
            "scene": name,
            "gaussians": int(prims.points.shape[0]),
            "held_out_frames": len(scene.frames[::HELD_OUT_EVERY]),
            **fitted.summary(),
            "fit_size": list(fitted.extra.get("fit_size", ())),
            "wall_s": round(time.perf_counter() - t0, 1),
            "cpu_s": round(time.process_time() - c0, 1),
        }
        rows.append(row)
        print(
            f"{name}: {row['gaussians']} Gaussians, {row['held_out_frames']} held-out frames, PSNR "
            f"{row['psnr_before']:.2f} -> {row['psnr_after']:.2f} dB, SSIM {row['ssim_before']:.3f} -> "
            f"{row['ssim_after']:.3f} ({row['iterations']} iterations at {row['fit_size']}, {row['wall_s']} s wall, "
            f"{row['cpu_s']} s CPU)",
            flush=True,
        )
    return rows


def _room_primitives(work: Path, copies: int) -> Any:
    from types import SimpleNamespace

    scene = open_bundle(_rooms_small(work))
    prims = build_primitives(scene, PrimitivesConfig())
    if copies == 1:
        return scene, prims
    rng = np.random.default_rng(0)
    points = np.concatenate([prims.points + rng.normal(0, 0.01, prims.points.shape) for _ in range(copies)])
    points = points.astype(np.float32)
    colors = np.concatenate([prims.colors] * copies)
    dense = SimpleNamespace(
        points=points,
        colors=colors,
        scales=gaussian_log_scales(points),
        opacities=np.zeros(len(points), np.float32),
    )
    return scene, dense


def _rooms_small(work: Path) -> Path:
    path = work / "small-default-0"
    if not (path / "scene.json").is_file():
        make_scene(path, preset="small", difficulty="default", seed=0)
    return path


def cost_case(work: Path, copies: int, width: int, iterations: int, render_only: bool) -> dict[str, Any]:
    """One cost case in this process: seconds per fit iteration (unless ``render_only``) and per render (forward
    only, with the top-weight ids of the label renders), and the peak RSS."""
    import torch

    from panogs_core.gaussians import resolve_schedule
    from panogs_core.gaussians.fit import Fitter
    from panogs_core.gaussians.rasterizer import rasterize

    scene, prims = _room_primitives(work, copies)
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    cfg = AppearanceConfig(fit_width=width, iterations=iterations, device="cpu")
    from panogs_core.gaussians import initial_gaussians

    start = initial_gaussians(prims, prims.colors)
    fitter = Fitter(scene, start, cfg, resolve_schedule(cfg, scene.camera.width, False))
    # the fit clamps its width to the camera's (320 here); a render may be larger, at the same field of view
    fitter.size = (width, round(scene.camera.height * width / scene.camera.width))
    frames = [f for f in scene.frames if f.color is not None]
    for f in frames:
        fitter.target(f)  # decode outside the timing
    fit_wall = fit_cpu = float("nan")
    if not render_only:
        t0, c0 = time.perf_counter(), time.process_time()
        fitter.train(frames, None)
        fit_wall, fit_cpu = (time.perf_counter() - t0) / iterations, (time.process_time() - c0) / iterations
    rss_fit = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    n = min(iterations, len(frames))
    t0, c0 = time.perf_counter(), time.process_time()
    with torch.no_grad():
        for f in frames[:n]:
            fitter.render(f, 0)
    render_wall, render_cpu = (time.perf_counter() - t0) / n, (time.process_time() - c0) / n
    t0, c0 = time.perf_counter(), time.process_time()
    with torch.no_grad():
        for f in frames[:n]:
            rasterize(fitter.gaussians(), torch.zeros(len(prims.points), 1), fitter.camera(f), with_top_index=True)
    top_wall = (time.perf_counter() - t0) / n
    return {
        "gaussians": int(prims.points.shape[0]),
        "size": list(fitter.size),
        "fit_s_per_iteration": round(fit_wall, 3),
        "fit_cpu_s_per_iteration": round(fit_cpu, 3),
        "render_s": round(render_wall, 3),
        "render_cpu_s": round(render_cpu, 3),
        "render_with_ids_s": round(top_wall, 3),
        "peak_rss_fit_mb": round(rss_fit, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "rss_before_mb": round(rss_before, 1),
        "threads": torch.get_num_threads(),
    }


def cost(work: Path, threads: int, iterations: int) -> list[dict[str, Any]]:
    _rooms_small(work)
    rows = []
    cases = [(1, 160), (1, 320), (5, 160), (5, 320), (5, 640)]
    for copies, width in cases:
        argv = [sys.executable, __file__, "_cost-case", "--copies", str(copies), "--width", str(width)]
        argv += ["--iterations", str(iterations), "--threads", str(threads), "--work", str(work)]
        argv += ["--render-only"] if width == 640 else []  # a 640 x 480 render is measured; a 640 fit is the GPU's
        done = subprocess.run(argv, check=True, capture_output=True, text=True, cwd=ROOT)
        row = json.loads(done.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(
            f"{row['gaussians']:>7} Gaussians at {row['size'][0]}x{row['size'][1]}: "
            f"fit {row['fit_s_per_iteration']} s/it ({row['fit_cpu_s_per_iteration']} CPU), "
            f"render {row['render_s']} s ({row['render_cpu_s']} CPU; with label ids {row['render_with_ids_s']} s), "
            f"peak RSS {row['peak_rss_mb']} MB (after the fit {row['peak_rss_fit_mb']}, "
            f"before {row['rss_before_mb']}), {row['threads']} thread(s)",
            flush=True,
        )
    return rows


def stage_time(work: Path, preset: str = "small") -> dict[str, Any]:
    """The stage at its default schedule on a synthetic room of ``preset`` (all colour frames fitted)."""
    path = _rooms_small(work) if preset == "small" else work / f"{preset}-0"
    if not (path / "scene.json").is_file():
        make_scene(path, preset=preset, difficulty="default", seed=0)
    scene = open_bundle(path)
    prims = build_primitives(scene, PrimitivesConfig())
    load_before = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    fitted = fit_appearance(scene, prims, prims.colors, AppearanceConfig(cpu_threads=None))  # --threads decides
    row = {
        **fitted.summary(),
        "wall_s": round(time.perf_counter() - t0, 1),
        "cpu_s": round(time.process_time() - c0, 1),
        "s_per_iteration": round(fitted.extra["seconds_per_iteration"], 3),
        "preset": preset,
        "gaussians": int(prims.points.shape[0]),
        "fit_size": list(fitted.extra.get("fit_size", ())),
        "load_average_before_after": [round(load_before, 2), round(os.getloadavg()[0], 2)],
    }
    print(
        f"{preset} room, {row['gaussians']} Gaussians: stage at the default CPU schedule: {row['iterations']} "
        f"iterations at {row['fit_size']}, {row['wall_s']} s wall, {row['cpu_s']} s "
        f"CPU ({row['s_per_iteration']} s/it); PSNR on training frames {row['psnr_before']} -> {row['psnr_after']} dB; "
        f"load average {row['load_average_before_after']} (before, after)",
        flush=True,
    )
    return row


TILE_SETTINGS = [(8, 64, 128), (8, 16, 128), (4, 128, 64), (4, 64, 64), (4, 64, 32), (2, 256, 64)]


def tiles(work: Path, sevenscenes: Path | None, stride: int, widths: list[int], steps: int) -> list[dict[str, Any]]:
    """CPU seconds per training step for each (width, tile settings), interleaved and repeated (module docstring)."""
    import torch

    from panogs_core.gaussians import initialise, resolve_schedule, split_frames
    from panogs_core.gaussians.fit import Fitter
    from panogs_core.gaussians.photometric import photometric_loss
    from panogs_core.gaussians.rasterizer import rasterize
    from panogs_core.gaussians.spherical_harmonics import sh_to_color

    bundle = _sevenscenes_bundle(work, sevenscenes, stride) if sevenscenes is not None else _rooms_small(work)
    scene = open_bundle(bundle)
    prims = build_primitives(scene, PrimitivesConfig())
    cfg = AppearanceConfig(held_out_every=HELD_OUT_EVERY)
    frames = split_frames(scene, cfg)[0]
    start = initialise(scene, prims, _initial_colors(scene, prims), frames, cfg)
    frames = frames[:steps]

    def step(fitter: Fitter, settings: tuple[int, int, int]) -> float:
        tile_size, per_batch, chunk = settings
        c0 = time.process_time()
        for frame in frames:
            cam, g = fitter.camera(frame), fitter.gaussians()
            rgb = sh_to_color(torch.cat([fitter.sh_dc, fitter.sh_rest], 1), g.means, cam.T_world_cam[:3, 3].float(), 0)
            image = rasterize(
                g, rgb, cam, tile_size=tile_size, tiles_per_batch=per_batch, chunk=chunk, analytic_backward=True
            ).features
            photometric_loss(image, fitter.target(frame)).backward()
        return (time.process_time() - c0) / len(frames)

    rows = []
    for width in widths:
        fit_cfg = AppearanceConfig(fit_width=width, device="cpu")
        fitter = Fitter(scene, start, fit_cfg, resolve_schedule(fit_cfg, scene.camera.width, False))
        step(fitter, TILE_SETTINGS[0])  # warm-up, and the targets decoded
        times: dict[tuple[int, int, int], list[float]] = {s: [] for s in TILE_SETTINGS}
        for _ in range(2):
            for settings in TILE_SETTINGS:
                times[settings].append(step(fitter, settings))
        for settings, seconds in times.items():
            row = {"gaussians": len(prims.points), "size": list(fitter.size), "tiles": list(settings)}
            row["cpu_s_per_step"] = [round(x, 4) for x in seconds]
            rows.append(row)
            print(
                f"{row['gaussians']} Gaussians at {fitter.size[0]}x{fitter.size[1]}, tile {settings[0]}, "
                f"{settings[1]} tiles per batch, chunk {settings[2]}: {row['cpu_s_per_step']} CPU s per step",
                flush=True,
            )
    return rows


def _sevenscenes_bundle(work: Path, src: Path, stride: int) -> Path:
    from panogs_core.io.importers.sevenscenes import import_sevenscenes

    bundle = work / f"sevenscenes-{src.resolve().parent.name}-stride{stride}"
    if not (bundle / "scene.json").is_file():
        if bundle.exists():
            shutil.rmtree(bundle)
        import_sevenscenes(src, bundle, stride=stride, placeholder_maps=True, name=src.resolve().parent.name)
    return bundle


def photometric_case(
    bundle: Path,
    schedule: str,
    init: str,
    eval_width: int,
    renders: Path | None,
    overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One (scene, schedule) case in this process: held-out PSNR / SSIM at ``eval_width``, fit time, peak memory.

    ``overrides``: AppearanceConfig fields set on top of the schedule's (``--set``).
    """
    import cv2
    import torch

    from panogs_core.gaussians import initialise, split_frames
    from panogs_core.gaussians.config import Schedule
    from panogs_core.gaussians.fit import Fitter

    scene = open_bundle(bundle)
    prims = build_primitives(scene, PrimitivesConfig())
    colors = _initial_colors(scene, prims)
    iterations = {"zero": None, "cpu": None, "gpu": None}[schedule]
    settings: dict[str, Any] = {
        "held_out_every": HELD_OUT_EVERY,
        "cpu_threads": None,
        "initialisation": init,
        "device": "cuda" if schedule == "gpu" else "cpu",
        "iterations": iterations,
        "enabled": schedule != "zero",
    }
    cfg = AppearanceConfig(**(settings | (overrides or {})))
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0, c0 = time.perf_counter(), time.process_time()
    if schedule == "zero":
        # The start the fit would take (a fit turned off keeps the primitives' own initialisation: fit_appearance).
        fit_frames, _, _ = split_frames(scene, cfg)
        fitted = initialise(scene, prims, colors, fit_frames, cfg)
    else:
        fitted = fit_appearance(scene, prims, colors, cfg)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    _, held, _ = split_frames(scene, cfg)
    device = "cuda" if schedule == "gpu" else "cpu"
    width = min(eval_width, scene.camera.width)
    judge = Fitter(scene, fitted, AppearanceConfig(sh_degree=fitted.sh_degree), Schedule(0, width, 1.0, device))
    scores = []
    with torch.no_grad():
        for frame in held:
            img = judge.render(frame, fitted.sh_degree).clamp(0, 1)
            target = judge.target(frame)
            from panogs_core.gaussians.photometric import psnr, ssim

            scores.append((psnr(img, target), float(ssim(img, target)), frame.id))
            if renders is not None and frame is held[0]:
                renders.mkdir(parents=True, exist_ok=True)
                pair = torch.cat([target, img], dim=1).mul(255).round().byte().cpu().numpy()
                cv2.imwrite(str(renders / f"{schedule}-{init}-{frame.id}.png"), pair[:, :, ::-1])
    return {
        "schedule": schedule,
        "init": init,
        "gaussians": int(prims.points.shape[0]),
        "iterations": fitted.iterations,
        "held_out_frames": len(held),
        "eval_size": list(judge.size),
        "fit_size": list(fitted.extra.get("fit_size", ())),
        "psnr": round(float(np.mean([s[0] for s in scores])), 2),
        "ssim": round(float(np.mean([s[1] for s in scores])), 3),
        "fit_wall_s": round(wall, 1),
        "fit_cpu_s": round(cpu, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "peak_rss_before_fit_mb": round(rss_before, 1),
        "cuda_peak_mb": round(torch.cuda.max_memory_allocated() / 2**20, 1) if torch.cuda.is_available() else None,
    }


def photometric(
    work: Path,
    sevenscenes: Path | None,
    stride: int,
    schedules: list[str],
    inits: list[str],
    eval_width: int,
    threads: int,
    renders: Path | None,
    scan: bool = False,
    overrides: list[str] | None = None,
) -> list[dict[str, Any]]:
    import torch

    scenes: dict[str, Path] = {}
    if sevenscenes is not None:
        scenes[f"7-Scenes {sevenscenes.resolve().parent.name} (stride {stride}, TSDF)"] = _sevenscenes_bundle(
            work, sevenscenes, stride
        )
    scenes["synthetic small default seed 0"] = _rooms_small(work)
    if scan:
        path = work / "scan-0"
        if not (path / "scene.json").is_file():
            make_scene(path, preset="scan", difficulty="default", seed=0)
        scenes["synthetic scan seed 0 (80k vertices)"] = path
    rows = []
    for name, bundle in scenes.items():
        for schedule in schedules:
            for init in inits if schedule != "gpu" else inits[:1]:
                if schedule == "gpu" and not torch.cuda.is_available():
                    row: dict[str, Any] = {"scene": name, "schedule": "gpu", "init": init, "note": "not run: no CUDA"}
                    rows.append(row)
                    print(f"{name}: gpu: not run (torch sees no CUDA device)", flush=True)
                    continue
                argv = [sys.executable, __file__, "_photometric-case", "--bundle", str(bundle)]
                argv += ["--schedule", schedule, "--init", init, "--eval-width", str(eval_width)]
                argv += ["--threads", str(threads), "--work", str(work)]
                argv += [a for o in overrides or [] for a in ("--set", o)]
                if renders is not None:
                    argv += ["--renders", str(renders / bundle.name)]
                done = subprocess.run(argv, check=True, capture_output=True, text=True, cwd=ROOT)
                row = {"scene": name, **json.loads(done.stdout.strip().splitlines()[-1])}
                rows.append(row)
                print(
                    f"{name}: {schedule} ({init} init): {row['gaussians']} Gaussians, {row['iterations']} iterations, "
                    f"held-out PSNR {row['psnr']} dB, SSIM {row['ssim']} at {row['eval_size']} "
                    f"({row['held_out_frames']} frames); fit {row['fit_wall_s']} s wall, {row['fit_cpu_s']} s CPU, "
                    f"peak RSS {row['peak_rss_mb']} MB (before the fit {row['peak_rss_before_fit_mb']}), "
                    f"CUDA peak {row['cuda_peak_mb']} MB",
                    flush=True,
                )
    return rows


def _overrides(pairs: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` pairs as AppearanceConfig fields; a VALUE that is not JSON is taken as a string."""
    out: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise SystemExit(f"--set: expected KEY=VALUE, got {pair!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "what", choices=["photometric", "quality", "cost", "stage", "tiles", "_cost-case", "_photometric-case"]
    )
    ap.add_argument("--sevenscenes", help="photometric: a 7-Scenes sequence folder (frame-*.color.jpg ...)")
    ap.add_argument("--stride", type=int, default=10, help="photometric: keep every n-th 7-Scenes frame")
    ap.add_argument("--schedules", nargs="+", default=["zero", "cpu", "gpu"], choices=["zero", "cpu", "gpu"])
    ap.add_argument("--inits", nargs="+", default=["surface"], choices=["surface", "reference"])
    ap.add_argument("--eval-width", type=int, default=320, help="photometric: px, width of the scored renders")
    ap.add_argument("--renders", help="photometric: write the first held-out render beside its frame here")
    ap.add_argument("--scan", action="store_true", help="photometric: add the synthetic scan room (80k vertices)")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="photometric: an AppearanceConfig field for every fitted case (VALUE read as JSON), repeatable",
    )
    ap.add_argument("--bundle", help=argparse.SUPPRESS)
    ap.add_argument("--schedule", help=argparse.SUPPRESS)
    ap.add_argument("--init", help=argparse.SUPPRESS)
    ap.add_argument("--work", default=str(WORK))
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    ap.add_argument("--iterations", type=int, default=5, help="cost: fit iterations; tiles: steps per setting")
    ap.add_argument("--widths", type=int, nargs="+", default=[80, 160], help="tiles: fit widths (px)")
    ap.add_argument("--copies", type=int, default=1)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--render-only", action="store_true", help="_cost-case: time the render only, no fit")
    ap.add_argument("--preset", default="small", help="stage: the synthetic room (small, scan, scannet-size, ...)")
    ap.add_argument("--json", help="also write the numbers to this JSON file")
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    result: Any
    if args.what == "_cost-case":
        print(json.dumps(cost_case(work, args.copies, args.width, args.iterations, args.render_only)))
        return
    if args.what == "_photometric-case":
        renders = Path(args.renders) if args.renders else None
        overrides = _overrides(args.set)
        print(
            json.dumps(
                photometric_case(Path(args.bundle), args.schedule, args.init, args.eval_width, renders, overrides)
            )
        )
        return
    if args.what == "photometric":
        result = photometric(
            work,
            Path(args.sevenscenes) if args.sevenscenes else None,
            args.stride,
            args.schedules,
            args.inits,
            args.eval_width,
            args.threads,
            Path(args.renders) if args.renders else None,
            args.scan,
            args.set,
        )
    elif args.what == "quality":
        result = quality(work)
    elif args.what == "tiles":
        sevenscenes = Path(args.sevenscenes) if args.sevenscenes else None
        result = tiles(work, sevenscenes, args.stride, args.widths, max(args.iterations, 12))
    elif args.what == "cost":
        result = cost(work, args.threads, args.iterations)
    else:
        result = stage_time(work, args.preset)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
