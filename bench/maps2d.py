"""2D-maps stage costs: time per key frame and peak memory of each supported model at its real size (docs/method.md
§17, docs/benchmarks.md "2D maps stage costs").

Usage:
    python bench/maps2d.py [--threads 2] [--frames 2] [--warm 0|1] [--masks 32] [--nms-iou 1.0]
                           [--cases sam-vit-b slimsam-77 ...] [--root DIR]
    python bench/maps2d.py --components [--dtype bfloat16]   # CPU s per part (encoder, decoder a point, crop), 1 thread
    python bench/maps2d.py --parts [--cases ...]   # where one key frame's CPU time goes inside the stage
    python bench/maps2d.py --profile-decoder   # where SAM's decoder time goes, per operator, one thread
    python bench/maps2d.py --room 100 --room-bundle DIR   # the whole stage on a room's key frames (below)

No weights can be downloaded here, so each model is built at its published architecture with random weights and
saved with ``save_pretrained`` (kept under ``--root``); random weights cost what real ones do, except where the work
depends on the outputs: the number of masks SAM keeps. So the mask cases keep every candidate up to the stage's
``max_candidates`` (the most the NMS sees), and the feature cases paint a fixed id map of ``--masks`` rectangles
(each embedded at every crop margin, plus the whole image). Frames are 640x480 (ScanNet's colour frames as the
reference resizes them; SAM resizes to 1024 and CLIP crops to 224 whatever the input, so the input size moves
little). Each case runs in its own process (peak memory is its own ``ru_maxrss``): one warm-up frame (``--warm 0``:
none, the timed run then includes the models' load), then ``--frames`` timed ones, each in a fresh checkpoint
folder. Prints a markdown table with wall time and CPU time (user + system) per frame: on a host that other
processes load, wall time grows with the load while CPU time stays the work's; the room estimate is CPU time /
threads (a perfect 2-core split, an upper bound on speed).

The children run with the thread environment ``panogs run`` and ``panogs worker`` give the stage
(panogs_core/threads.py: ``--threads`` threads per pool, idle threads sleep at once); ``--active-wait`` keeps the
OpenMP default instead (idle threads spin, which a loaded host bills as CPU time: how the figures before
2026-12-05 09:00 UTC were taken).

``--room N --room-bundle DIR``: the whole stage as a run calls it (``with_computed_maps``, bundle frames read,
maps written to a checkpoint folder) on ``N`` key frames of a bundle (the frames that bring masks, e.g. a
``scannet-size`` synthetic room's 100), copied without their maps and without the other frames; the CPU default
models at their real sizes, every candidate kept as in the cases (with the stage's filters, random weights leave
no mask and only the whole image is embedded). Prints one JSON line: wall and CPU seconds, per frame, peak RSS.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

HEIGHT, WIDTH = 480, 640

# Published architectures (the hub's config.json of each; SlimSAM-77: a SAM ViT-B pruned to width 168).
SAM_ARCH = {
    "sam-vit-b": {},
    "slimsam-77": {"hidden_size": 168, "mlp_dim": 696},
}
CLIP_ARCH = {
    "clip-b32": (
        {
            "hidden_size": 768,
            "intermediate_size": 3072,
            "num_hidden_layers": 12,
            "num_attention_heads": 12,
            "patch_size": 32,
        },
        {"hidden_size": 512, "intermediate_size": 2048, "num_attention_heads": 8},
        512,
    ),
    "clip-b16": (
        {
            "hidden_size": 768,
            "intermediate_size": 3072,
            "num_hidden_layers": 12,
            "num_attention_heads": 12,
            "patch_size": 16,
        },
        {"hidden_size": 512, "intermediate_size": 2048, "num_attention_heads": 8},
        512,
    ),
    "clip-l14": (
        {
            "hidden_size": 1024,
            "intermediate_size": 4096,
            "num_hidden_layers": 24,
            "num_attention_heads": 16,
            "patch_size": 14,
        },
        {"hidden_size": 768, "intermediate_size": 3072, "num_attention_heads": 12},
        768,
    ),
}
# case name -> (masks model, features model, settings)
CASES = {
    "sam-vit-b": ("sam-vit-b", None, {"points_per_side": 32}),
    "slimsam-77": ("slimsam-77", None, {"points_per_side": 32}),
    "slimsam-77-p16": ("slimsam-77", None, {"points_per_side": 16}),
    "clip-b32": (None, "clip-b32", {}),
    "clip-b16": (None, "clip-b16", {}),
    "clip-b16-1crop": (None, "clip-b16", {"crop_margins": (0.1,)}),
    "clip-l14": (None, "clip-l14", {}),
    "slimsam-77-p8": ("slimsam-77", None, {"points_per_side": 8}),
    # the CPU default before 2026-12-05 (two crop margins, 64 prompts per decoder call)
    "slimsam-77-p16+clip-b16": ("slimsam-77", "clip-b16", {"points_per_side": 16, "points_per_batch": 64}),
    # the CPU default (docs/method.md §17); cpu_precision "auto": bfloat16 on a CPU with AVX512-BF16 or AMX
    "slimsam-77-p8+clip-b32": ("slimsam-77", "clip-b32", {"points_per_side": 8}),
    # the GPU default (docs/method.md §17): SAM ViT-B at SAM's 32x32 grid (points_per_side None on CUDA), ViT-B/16
    "sam-vit-b+clip-b16": ("sam-vit-b", "clip-b16", {}),
    # the CPU default in float32 (the default before 2026-12-05 10:00 UTC, and on a CPU without native bfloat16)
    "slimsam-77-p8+clip-b32-fp32": ("slimsam-77", "clip-b32", {"points_per_side": 8, "cpu_precision": "float32"}),
    "slimsam-77-p8+clip-b32-1crop": ("slimsam-77", "clip-b32", {"points_per_side": 8, "crop_margins": (0.1,)}),
}
KEEP_ALL = {"pred_iou_thresh": -1.0, "stability_score_thresh": 0.0, "min_mask_fraction": 0.0}


def build(name: str, root: Path) -> Path:
    """The model's folder under ``root``, saved once with random weights."""
    folder = root / name
    if (folder / "config.json").is_file():
        return folder
    import torch

    torch.manual_seed(0)
    if name in SAM_ARCH:
        from transformers import SamConfig, SamImageProcessorPil, SamModel

        SamModel(SamConfig(vision_config=SAM_ARCH[name])).save_pretrained(folder)
        SamImageProcessorPil().save_pretrained(folder)
    else:
        from transformers import CLIPConfig, CLIPImageProcessorPil, CLIPModel

        vision, text, dim = CLIP_ARCH[name]
        CLIPModel(CLIPConfig(vision_config=vision, text_config=text, projection_dim=dim)).save_pretrained(folder)
        CLIPImageProcessorPil().save_pretrained(folder)
    return folder


def frames(count: int, masks: int | None):
    """Synthetic 640x480 frames; with ``masks``, an id map of that many rectangles (a features-only run)."""
    from panogs_core.stages.maps2d import FrameImage

    rng = np.random.default_rng(0)
    ids = None
    if masks:
        side = int(np.ceil(np.sqrt(masks)))
        rows = np.minimum(np.arange(HEIGHT) * side // HEIGHT, side - 1)
        cols = np.minimum(np.arange(WIDTH) * side // WIDTH, side - 1)
        ids = (rows[:, None] * side + cols[None, :] + 1).astype(np.int64)
        ids[ids > masks] = 0
    for i in range(count):
        image = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
        yield FrameImage(f"{i:06d}", image, ids)


def run_case(name: str, args: argparse.Namespace) -> dict[str, object]:
    """One case in this process: warm-up frame, then the timed frames."""
    import torch

    from panogs_core.stages.maps2d import Maps2DConfig, compute_2d_maps

    torch.set_num_threads(args.threads)
    masks_name, feats_name, extra = CASES[name]
    root = Path(args.root)
    masks_dir = build(masks_name, root / "models") if masks_name else None
    feats_dir = build(feats_name, root / "models") if feats_name else None
    nms = {} if args.nms_iou is None else {"nms_iou_thresh": args.nms_iou}
    cfg = Maps2DConfig(device=args.device, **KEEP_ALL, **{"max_masks": args.masks, **nms, **extra})
    n_masks = None if masks_dir else args.masks
    out = root / "runs" / name
    shutil.rmtree(out, ignore_errors=True)  # a kept folder would be continued, not computed
    start = time.perf_counter()
    if args.warm:
        compute_2d_maps(frames(1, n_masks), out / "warm", cfg, masks_model=masks_dir, features_model=feats_dir)
    warm = time.perf_counter() - start
    cpu_before = _cpu_seconds()
    start = time.perf_counter()
    result = compute_2d_maps(
        frames(args.frames, n_masks), out / "timed", cfg, masks_model=masks_dir, features_model=feats_dir
    )
    per_frame = (time.perf_counter() - start) / args.frames
    cpu_per_frame = (_cpu_seconds() - cpu_before) / args.frames
    sizes = [p.stat().st_size for p in (out / "timed").rglob("*") if p.suffix in (".png", ".npy")]
    return {
        "case": name,
        "per_frame_s": per_frame,
        "cpu_per_frame_s": cpu_per_frame,
        "first_s": warm,
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "masks": [f.mask_count for f in result.frames],
        "bytes_per_frame": sum(sizes) / args.frames,
        "cuda_peak_mb": torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else None,
    }


def run_components(args: argparse.Namespace) -> None:
    """CPU seconds of each model's parts on one thread: SAM's image encoder per frame and decoder per prompt
    point, CLIP's image tower per 224-px crop (a batch of 8). Prints one JSON line each."""
    import torch
    from transformers import CLIPModel, SamModel

    torch.set_num_threads(1)
    root = Path(args.root) / "models"
    dtype = getattr(torch, args.dtype)
    print(json.dumps({"dtype": args.dtype}))
    with torch.inference_mode():
        for name in CLIP_ARCH:
            clip = CLIPModel.from_pretrained(build(name, root), dtype=dtype).eval()
            crops = torch.randn(8, 3, 224, 224, dtype=dtype)
            clip.get_image_features(pixel_values=crops[:1])
            before = _cpu_seconds()
            clip.get_image_features(pixel_values=crops)
            print(json.dumps({"model": name, "cpu_s_per_crop": round((_cpu_seconds() - before) / 8, 3)}), flush=True)
            del clip
        for name in SAM_ARCH:
            sam = SamModel.from_pretrained(build(name, root), dtype=dtype).eval()
            before = _cpu_seconds()
            embeddings = sam.get_image_embeddings(torch.randn(1, 3, 1024, 1024, dtype=dtype))
            encoder = _cpu_seconds() - before
            row: dict[str, object] = {"model": name, "encoder_cpu_s": round(encoder, 2)}
            for batch in (4, 64):  # prompts per decoder call: the stage's CPU value, and SAM's
                row[f"decoder_cpu_s_per_point_batch_{batch}"] = round(_decoder_cpu_per_point(sam, embeddings, batch), 3)
            print(json.dumps(row), flush=True)
            del sam


def _decoder_cpu_per_point(sam: Any, embeddings: Any, batch: int, points: int = 64) -> float:
    """CPU seconds per prompt point of SAM's prompt encoder and mask decoder, ``points`` points in calls of
    ``batch`` (after one warm-up call)."""
    import torch

    grid = (torch.rand(1, points, 1, 2) * 1000).to(embeddings.dtype)
    labels = torch.ones(1, batch, 1, dtype=torch.long)
    sam(image_embeddings=embeddings, input_points=grid[:, :batch], input_labels=labels)
    before = _cpu_seconds()
    for start in range(0, points, batch):
        sam(image_embeddings=embeddings, input_points=grid[:, start : start + batch], input_labels=labels)
    return (_cpu_seconds() - before) / points


def run_parts(name: str, args: argparse.Namespace) -> dict[str, object]:
    """CPU seconds per key frame of each part of the stage's frame step (the functions it calls, wrapped), after
    a warm-up frame, in this process: SAM's encoder, the decoder loop with its filters, NMS, painting, the crops'
    embedding (processor and tower) and the tower alone."""
    import torch

    from panogs_core.stages.maps2d import features, masks, runner
    from panogs_core.stages.maps2d.config import Maps2DConfig

    torch.set_num_threads(args.threads)
    masks_name, feats_name, extra = CASES[name]
    root = Path(args.root) / "models"
    cfg = Maps2DConfig(device="cpu", **KEEP_ALL, **{"max_masks": args.masks, **extra})
    models = runner.load_models(
        build(masks_name, root) if masks_name else None, build(feats_name, root) if feats_name else None, cfg
    )
    spent: dict[str, float] = {}

    def wrap(owner: Any, attr: str, label: str) -> None:
        inner = getattr(owner, attr)

        def timed(*a: Any, **k: Any) -> Any:
            before = _cpu_seconds()
            try:
                return inner(*a, **k)
            finally:
                spent[label] = spent.get(label, 0.0) + _cpu_seconds() - before

        setattr(owner, attr, timed)

    if models.sam is not None:
        wrap(models.sam.model, "get_image_embeddings", "sam_encoder")
    wrap(masks, "_candidates", "decoder_and_filters")
    wrap(masks, "mask_nms", "nms")
    wrap(masks, "paint_masks", "paint")
    wrap(features, "_embed", "crops_embedded")
    if models.clip is not None:
        wrap(models.clip.model, "forward", "image_tower")
    images = list(frames(args.frames + 1, None if masks_name else args.masks))
    runner.process_frame(models, images[0].color, images[0].masks, cfg)  # warm-up
    spent.clear()
    before, start = _cpu_seconds(), time.perf_counter()
    for image in images[1:]:
        out = runner.process_frame(models, image.color, image.masks, cfg)
    n = args.frames
    return {
        "case": name,
        "dtype": str((models.sam or models.clip).dtype).removeprefix("torch."),  # type: ignore[union-attr]
        "cpu_s_per_frame": round((_cpu_seconds() - before) / n, 2),
        "wall_s_per_frame": round((time.perf_counter() - start) / n, 2),
        **{k: round(v / n, 2) for k, v in spent.items()},
        "masks": out.mask_count,
        "peak_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
    }


def run_decoder_profile() -> None:
    """Where SAM's decoder spends its CPU time per point, and its floating-point work per point:
    ``SamMaskDecoder`` alone (SAM ViT-B's default decoder config, random weights), 64 single-point prompts on a
    random image embedding, one thread, no post-processing; prints the CPU seconds and GFLOP (torch's
    FlopCounterMode) per point and torch.profiler's operators by self CPU time."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode
    from transformers import SamConfig
    from transformers.models.sam.modeling_sam import SamMaskDecoder

    torch.set_num_threads(1)
    decoder = SamMaskDecoder(SamConfig().mask_decoder_config).eval()
    embedding, position, dense = (torch.randn(1, 256, 64, 64) for _ in range(3))
    sparse = torch.randn(1, 64, 2, 256)  # 64 prompts, a point and its padding token each
    kwargs = {"image_embeddings": embedding, "image_positional_embeddings": position,
              "dense_prompt_embeddings": dense, "multimask_output": True}  # fmt: skip
    with torch.inference_mode():
        decoder(sparse_prompt_embeddings=sparse[:, :2], **kwargs)  # warm-up
        with torch.profiler.profile() as prof:
            before = _cpu_seconds()
            decoder(sparse_prompt_embeddings=sparse, **kwargs)
            per_point = (_cpu_seconds() - before) / 64
    with torch.inference_mode(), FlopCounterMode(display=False) as flops:
        decoder(sparse_prompt_embeddings=sparse[:, :4], **kwargs)
    gflop = flops.get_total_flops() / 4 / 1e9  # per prompt: the decoder's work grows linearly with the prompts
    print(json.dumps({"decoder_cpu_s_per_point": round(per_point, 3), "decoder_gflop_per_point": round(gflop, 2)}))
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=12))


def room_bundle(src: Path, dst: Path, count: int) -> Path:
    """A copy of bundle ``src`` (scene.json and the colour images it keeps) with its first ``count`` key frames
    (frames that bring masks) and no maps: what a capture without maps looks like to the stage."""
    doc = json.loads((src / "scene.json").read_text())
    keys = [f for f in doc["frames"] if f.get("masks")][:count]
    if len(keys) < count:
        raise SystemExit(f"{src}: {len(keys)} key frames, fewer than --room {count}")
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("masks", "features", "color", "depth"))
    for frame in keys:
        frame.pop("masks")
        frame.pop("features", None)
        for kind in ("color", "depth"):
            (dst / frame[kind]).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / frame[kind], dst / frame[kind])
    doc["frames"] = keys
    doc.pop("features", None)
    (dst / "scene.json").write_text(json.dumps(doc))
    return dst


def run_room(args: argparse.Namespace) -> dict[str, object]:
    """The stage on ``--room`` key frames of ``--room-bundle`` in this process (its entry as a run calls it)."""
    from panogs_core.io.bundle import open_bundle
    from panogs_core.stages.maps2d import MapModels, Maps2DConfig
    from panogs_core.stages.maps2d.stage import with_computed_maps
    from panogs_core.threads import set_torch_threads

    set_torch_threads(args.threads)
    root = Path(args.root)
    masks_name, feats_name, extra = CASES[args.room_case]
    models = MapModels(
        str(build(masks_name, root / "models")) if masks_name else None,
        str(build(feats_name, root / "models")) if feats_name else None,
    )
    bundle = open_bundle(room_bundle(Path(args.room_bundle), root / "room" / "bundle", args.room))
    checkpoints = root / "room" / "stages"
    shutil.rmtree(checkpoints, ignore_errors=True)
    done: list[float] = []
    cpu_before, start = _cpu_seconds(), time.perf_counter()

    def progress(count: int, total: int) -> None:
        done.append(time.perf_counter() - start)
        load = os.getloadavg()[0]
        print(f"# frame {count}/{total} at {done[-1]:.0f} s, load {load:.1f}", file=sys.stderr, flush=True)

    cfg = Maps2DConfig(device="cpu", **KEEP_ALL, **{"max_masks": args.masks, **extra})  # as the cases: masks flow
    result = with_computed_maps(bundle, checkpoints, cfg, models, progress).computed
    wall, cpu = time.perf_counter() - start, _cpu_seconds() - cpu_before
    frames = len(result.frames)  # type: ignore[union-attr]
    return {
        "case": args.room_case,
        "frames": frames,
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "wall_s_per_frame": round(wall / frames, 2),
        "cpu_s_per_frame": round(cpu / frames, 2),
        "first_frame_wall_s": round(done[0], 1),
        "peak_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "masks_per_frame": round(sum(f.mask_count for f in result.frames) / frames, 1),  # type: ignore[union-attr]
    }


def _cpu_seconds() -> float:
    """User + system CPU seconds of this process: on a host other processes load, the work itself."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu", help="the cases' maps2d.device (cuda: bench/gpu_check.sh)")
    parser.add_argument("--frames", type=int, default=2, help="timed frames per case (after one warm-up)")
    parser.add_argument("--masks", type=int, default=32, help="masks per frame: max_masks, and the features' id map")
    parser.add_argument(
        "--nms-iou",
        type=float,
        help="the mask cases' NMS threshold (1.0: only identical masks suppressed, so about --masks masks reach "
        "the features, as a real room's frame gives; default: the stage's, which leaves 10-13 random masks)",
    )
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--warm", type=int, default=1, choices=(0, 1), help="0: no warm-up frame (the timed run loads)")
    parser.add_argument("--root", default="/tmp/maps2d-bench")
    parser.add_argument("--components", action="store_true", help="per-part CPU seconds on one thread instead")
    parser.add_argument("--profile-decoder", action="store_true", help="SAM's decoder alone, profiled, one thread")
    parser.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"), help="--components' dtype")
    parser.add_argument("--parts", action="store_true", help="per-part CPU s of a key frame inside the stage")
    parser.add_argument(
        "--active-wait", action="store_true", help="keep OpenMP's spinning idle threads (the figures before 09:00 UTC)"
    )
    parser.add_argument("--room", type=int, help="the whole stage on this many key frames of --room-bundle")
    parser.add_argument("--room-bundle", help="a bundle whose key frames bring masks (a scannet-size synthetic room)")
    parser.add_argument("--room-case", default="slimsam-77-p8+clip-b32", choices=[c for c in CASES if "+" in c])
    parser.add_argument("--one", help=argparse.SUPPRESS)  # internal: run one case, print its JSON
    args = parser.parse_args()
    if not args.active_wait and os.environ.get("OMP_WAIT_POLICY") is None:
        # as `panogs run` does (panogs_core/cli/arguments.py limit_threads), for the children: their pools read it
        # when they load; then run again so that this process's own pools do too
        from panogs_core.threads import apply_thread_environment

        apply_thread_environment(os.environ, args.threads)
        os.execv(sys.executable, [sys.executable, *sys.argv])
    if args.room:
        if not args.room_bundle:
            parser.error("--room needs --room-bundle")
        print(json.dumps(run_room(args)))
        return
    if args.components:
        run_components(args)
        return
    if args.profile_decoder:
        run_decoder_profile()
        return
    if args.one:
        print(json.dumps(run_parts(args.one, args) if args.parts else run_case(args.one, args)))
        return
    if args.parts:  # each case in its own process (its own peak)
        for name in args.cases:
            argv = [sys.executable, __file__, "--parts", "--one", name, "--threads", str(args.threads),
                    "--frames", str(args.frames), "--masks", str(args.masks), "--root", args.root,
                    *(["--active-wait"] if args.active_wait else [])]  # fmt: skip
            proc = subprocess.run(argv, capture_output=True, text=True, check=False)
            lines = proc.stdout.strip().splitlines()
            print(lines[-1] if proc.returncode == 0 and lines else f"{name}: failed: {proc.stderr[-400:]}", flush=True)
        return
    print(
        f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.processor() or platform.machine()}, "
        f"load {os.getloadavg()[0]:.2f}, {args.threads} threads, {args.frames} timed frames, {args.masks} masks, "
        f"NMS {args.nms_iou if args.nms_iou is not None else 'the stage default'}, "
        f"OMP_WAIT_POLICY {os.environ.get('OMP_WAIT_POLICY', 'unset (spinning)')}, device {args.device}"
    )
    print(
        "| case | wall s / key frame | CPU s / key frame | first frame wall s | peak RSS MB | masks "
        "| MB written / frame "
        "| 100 frames, min (CPU s / threads) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name in args.cases:
        argv = [
            sys.executable,
            __file__,
            "--one",
            name,
            "--threads",
            str(args.threads),
            "--frames",
            str(args.frames),
            "--masks",
            str(args.masks),
            "--warm",
            str(args.warm),
            "--root",
            args.root,
            "--device",
            args.device,
            *(["--nms-iou", str(args.nms_iou)] if args.nms_iou is not None else []),
            *(["--active-wait"] if args.active_wait else []),
        ]
        proc = subprocess.run(argv, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            print(f"| {name} | failed: {proc.stderr.strip().splitlines()[-1]} |")
            continue
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        room_min = row["cpu_per_frame_s"] / args.threads * 100 / 60
        print(
            f"| {name} | {row['per_frame_s']:.2f} | {row['cpu_per_frame_s']:.2f} | {row['first_s']:.2f} | "
            f"{row['peak_mb']:.0f} | {max(row['masks'])} | {row['bytes_per_frame'] / 1e6:.2f} | {room_min:.1f} |",
            flush=True,
        )
    print(f"# load after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
