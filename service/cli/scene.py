"""`symgs info` and `symgs render`: look at a scene without compressing it."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from .parser import CliError, check_input, check_output, error_text

DEFAULT_ORBIT_SIZE = 512
DEFAULT_ORBIT_VIEWS = 8


def register(subparsers: argparse._SubParsersAction) -> None:
    info = subparsers.add_parser(
        "info",
        help="describe a scene: Gaussian count, SH degree, bounds, properties, repairs",
        description="Read a graphdeco .ply scene and describe it: Gaussian count, SH degree, bounds, the property "
        "order found, ignored properties and any repairs made while reading.",
    )
    info.add_argument("scene", type=Path, help="scene .ply (graphdeco layout, SH degree 0..3)")
    info.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    info.set_defaults(func=run_info)

    render = subparsers.add_parser(
        "render",
        help="render one view of a scene to an image",
        description="Render a scene from a dataset camera (--dataset DIR --view I) or from one of N cameras spread "
        "over the scene's bounding sphere (--orbit I). With a dataset, PSNR and SSIM against its image are printed.",
    )
    render.add_argument("scene", type=Path, help="scene .ply")
    source = render.add_mutually_exclusive_group(required=True)
    source.add_argument("--dataset", type=Path, metavar="DIR", help="NeRF-Synthetic or COLMAP dataset folder")
    source.add_argument("--orbit", type=int, metavar="I", help="index of an orbit camera (0..views-1)")
    render.add_argument("--view", type=int, metavar="I", help="index of the dataset view (with --dataset)")
    render.add_argument(
        "--split", default="all", choices=["train", "val", "test", "all"], help="dataset split the view index counts in"
    )
    render.add_argument(
        "--views", type=int, default=DEFAULT_ORBIT_VIEWS, metavar="N", help="orbit cameras (default %(default)s)"
    )
    render.add_argument("-o", "--output", type=Path, required=True, metavar="OUT.png", help="image to write")
    render.add_argument("--width", type=int, help=f"image width (default: the dataset's, or {DEFAULT_ORBIT_SIZE})")
    render.add_argument("--height", type=int, help="image height (default: keeps the aspect ratio)")
    render.add_argument(
        "--up", default="0,0,1", metavar="X,Y,Z", help="world up for orbit cameras (default z up; 0,-1,0 for COLMAP)"
    )
    render.add_argument("--background", default="1,1,1", metavar="R,G,B", help="background in [0, 1] (default white)")
    render.add_argument("--backend", default="auto", choices=["auto", "cpu", "gsplat"], help="rasterizer")
    render.set_defaults(func=run_render)


def _read(path: Path) -> tuple[Any, Any]:
    from symgs_core.ply import PlyError, read_scene

    check_input("scene file", path)
    try:
        return read_scene(path)
    except PlyError as exc:
        raise CliError(f"cannot read {path}: {error_text(exc)}") from None


def _compact(names: list[str]) -> str:
    """Property names with the run of f_rest_* written as one range."""
    rest = [n for n in names if n.startswith("f_rest_")]
    out: list[str] = []
    for name in names:
        if name.startswith("f_rest_"):
            if name == rest[0]:
                out.append(f"f_rest_0..{len(rest) - 1}" if len(rest) > 1 else name)
            continue
        out.append(name)
    return " ".join(out)


def describe(path: Path) -> dict[str, Any]:
    """Everything `symgs info` reports, as plain JSON-able values."""
    from symgs_core.cameras import scene_bounds

    scene, report = _read(path)
    means = scene.means.double()
    empty = len(scene) == 0
    center, radius = scene_bounds(scene.means, scene.scales)
    return {
        "file": str(path),
        "count": report.count,
        "sh_degree": report.sh_degree,
        "format": report.format,
        "layout": report.layout,
        "bounds": {
            "min": [] if empty else means.min(dim=0).values.tolist(),
            "max": [] if empty else means.max(dim=0).values.tolist(),
        },
        "center": center.tolist(),
        "radius": radius,
        "properties": report.properties,
        "ignored": report.ignored,
        "repairs": report.repairs,
        "comments": report.comments,
    }


def run_info(args: argparse.Namespace) -> int:
    info = describe(args.scene)
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    lo, hi = info["bounds"]["min"], info["bounds"]["max"]
    bounds = (
        "  ".join(f"{axis} [{a:.4g}, {b:.4g}]" for axis, a, b in zip("xyz", lo, hi, strict=True)) if lo else "empty"
    )
    repairs = ", ".join(f"{name}: {count}" for name, count in info["repairs"].items()) or "none"
    rows = [
        ("scene", info["file"]),
        ("gaussians", f"{info['count']:,}"),
        ("sh degree", str(info["sh_degree"])),
        ("format", info["format"] + (" (PlayCanvas compressed)" if info["layout"] == "compressed" else "")),
        ("bounds", bounds),
        ("centre", "({:.4g}, {:.4g}, {:.4g})".format(*info["center"]) + f"  radius {info['radius']:.4g}"),
        ("properties", f"{_compact(info['properties'])}  ({len(info['properties'])})"),
        ("ignored", " ".join(info["ignored"]) or "none"),
        ("repairs", repairs),
    ]
    for label, value in rows:
        print(f"{label:<11} {value}")
    return 0


def _triple(option: str, text: str, low: float, high: float, example: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(low <= v <= high for v in values):
        raise CliError(f"{option} must be three numbers in [{low:g}, {high:g}] like {example}; got {text!r}")
    return values


def _size(width: int | None, height: int | None, native: tuple[int, int]) -> tuple[int, int]:
    """Output size: the given one, the native one, or one side given and the other keeping the aspect ratio."""
    for name, value in (("--width", width), ("--height", height)):
        if value is not None and not 1 <= value <= 16384:
            raise CliError(f"{name} must be in 1..16384, got {value}")
    w0, h0 = native
    if width is not None and height is not None:
        return width, height
    if width is not None:
        return width, max(1, round(width * h0 / w0))
    if height is not None:
        return max(1, round(height * w0 / h0)), height
    return w0, h0


def _pick_camera(args: argparse.Namespace, scene: Any) -> tuple[Any, Any, str]:
    """The camera to render, the dataset frame it came from (or None) and a label."""
    from symgs_core.cameras import orbit_cameras, scene_bounds
    from symgs_core.datasets import DatasetError, dataset_frames

    if args.dataset is not None:
        if args.view is None:
            raise CliError("--dataset needs --view I")
        try:
            frames = dataset_frames(args.dataset, args.split)
        except DatasetError as exc:
            raise CliError(f"cannot read dataset {args.dataset}: {error_text(exc)}") from None
        if not 0 <= args.view < len(frames):
            raise CliError(
                f"view {args.view} is out of range: split {args.split!r} has {len(frames)} views (0..{len(frames) - 1})"
            )
        frame = frames[args.view]
        camera = frame.camera
        width, height = _size(args.width, args.height, (camera.width, camera.height))
        return camera.resized(width, height), frame, f"view {args.view} ({frame.name}) of {len(frames)}"
    if args.view is not None:
        raise CliError("--view goes with --dataset; use --orbit I for cameras around the scene")
    if args.views < 1:
        raise CliError(f"--views must be at least 1, got {args.views}")
    if not 0 <= args.orbit < args.views:
        raise CliError(f"orbit camera {args.orbit} is out of range: --views {args.views} gives 0..{args.views - 1}")
    if len(scene) == 0:
        raise CliError("the scene has no Gaussians to frame an orbit around")
    up = _triple("--up", args.up, -1e9, 1e9, "0,0,1")
    norm = sum(v * v for v in up) ** 0.5
    if norm == 0:
        raise CliError("--up must not be the zero vector")
    up = (up[0] / norm, up[1] / norm, up[2] / norm)
    width, height = _size(args.width, args.height, (DEFAULT_ORBIT_SIZE, DEFAULT_ORBIT_SIZE))
    center, radius = scene_bounds(scene.means, scene.scales)
    camera = orbit_cameras(center, radius, args.views, width, height, up=up)[args.orbit]
    return camera, None, f"orbit camera {args.orbit} of {args.views}"


def run_render(args: argparse.Namespace) -> int:
    import numpy as np
    import torch
    from PIL import Image

    from symgs_core.datasets import DatasetError, composite, read_frame
    from symgs_core.metrics import psnr, ssim
    from symgs_core.render import BackendUnavailableError, render

    background = _triple("--background", args.background, 0.0, 1.0, "1,1,1")
    check_output("-o", args.output)
    scene, _ = _read(args.scene)
    camera, frame, label = _pick_camera(args, scene)
    device = "cuda" if args.backend == "gsplat" or (args.backend == "auto" and torch.cuda.is_available()) else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise CliError("--backend gsplat needs a CUDA device; use --backend cpu")
    start = time.perf_counter()
    try:
        with torch.no_grad():
            result = render(
                scene.to(device), camera.to(device), torch.tensor(background, device=device), backend=args.backend
            )
    except BackendUnavailableError as exc:
        raise CliError(str(exc)) from None
    seconds = time.perf_counter() - start
    image = result.image.detach().float().cpu().clamp(0.0, 1.0)

    pixels = (image.numpy() * 255.0 + 0.5).astype(np.uint8)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    try:
        Image.fromarray(pixels, "RGB").save(args.output)
    except (ValueError, KeyError, OSError) as exc:
        raise CliError(f"cannot write {args.output}: {exc}") from None
    backend = result.aux.get("backend", args.backend)
    print(f"wrote {args.output} ({camera.width}x{camera.height}, {label}, {backend} backend, {seconds:.2f} s)")
    if frame is not None:
        try:
            reference = composite(*read_frame(frame, camera.width, camera.height), background)
        except DatasetError as exc:
            raise CliError(f"cannot read the dataset image: {error_text(exc)}") from None
        if min(camera.width, camera.height) >= 11:
            fidelity = f"PSNR {float(psnr(image, reference)):.2f} dB, SSIM {float(ssim(image, reference)):.4f}"
            print(f"against {frame.name}: {fidelity}")
    return 0
