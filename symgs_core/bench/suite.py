"""A bench over several scenes, written to one folder:

    bench.json                     every row (``rows.BenchRow``), the claims and their check, settings and stamp
    bench.md                       the tables (``tables.markdown``)
    charts/rate_distortion.png     all scenes; charts/rate_distortion_<scene>.png per scene
    charts/speed_accuracy.png      all scenes; charts/speed_accuracy_<scene>.png per scene
    files/<scene>/...              every output, as the rows' ``file`` names it
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from ..views import DISTANCES
from . import stamp
from .rows import SCHEMA, TOLERANCE_DB, BenchRow, claims
from .run import BenchSettings, bench_scene, scene_name


def _kind(ply: Path, trained: bool) -> str | None:
    """Why ``ply`` counts as decoded from a quantised container, or None when it is as a trainer wrote it: as the
    caller said (``trained``), or else as its values say."""
    if trained:
        return None
    from ..ply import load_scene
    from .kinds import container_grid

    return container_grid(load_scene(ply))


def _names(scenes: list[Path]) -> list[str]:
    """A distinct name per scene (a second scene of the same name gets a numbered suffix)."""
    names: list[str] = []
    for ply in scenes:
        name = re.sub(r"[^A-Za-z0-9_.-]+", "_", scene_name(ply))
        names.append(name if name not in names else f"{name}-{sum(n.startswith(name) for n in names) + 1}")
    return names


def document(rows: list[BenchRow], scenes: list[Path], names: list[str], settings: BenchSettings,
             info: dict[str, Any], trained: list[bool | None], grids: list[str | None]) -> dict[str, Any]:  # fmt: skip
    """The content of ``bench.json``; ``grids``: per scene, why it counts as decoded from a container."""
    base = settings.config("balanced")
    found = claims(rows)
    return {
        "schema": SCHEMA,
        "generated": info,
        "settings": {
            "presets": list(settings.presets), "mirrors": list(settings.mirrors), "overrides": settings.overrides,
            "curve": settings.curve_method, "sweep_runs": settings.sweep, "peer_timeout_s": settings.peer_timeout,
            "slow_peer_timeout_s": settings.slow_timeout, "tolerance_db": TOLERANCE_DB,
            "config": {k: v for k, v in asdict(base).items() if k not in ("preset", "psnr_budget", "use_mirrors")},
        },
        "cameras": {
            "evaluation": {"seed": base.seed, "views": base.eval_views, "resolution": base.eval_resolution,
                           "distances": list(DISTANCES),
                           "note": "the runs' own evaluation cameras; they fit on other (fitting) cameras"},
            "other": {"seed": settings.other_seed, "views": settings.other_views, "resolution": base.eval_resolution,
                      "distances": list(DISTANCES), "note": "an independent rig: other directions"},
        },  # fmt: skip
        # The file's name, not where it lay: bench.json travels between machines.
        "scenes": [{"scene": name, "input": ply.name, "bytes": ply.stat().st_size, "trained": kind, "grid": grid}
                   for ply, name, kind, grid in zip(scenes, names, trained, grids)],  # fmt: skip
        "rows": [r.as_json() for r in rows],
        "claims": found,
        "claims_failing_on_other_cameras": [c for c in found if c["holds_on_other_cameras"] is False],
    }


def write_charts(rows: list[BenchRow], input_bytes: dict[str, int], folder: Path) -> list[Path]:
    from . import charts

    folder.mkdir(parents=True, exist_ok=True)
    made = {
        "rate_distortion.png": charts.rate_distortion_overall_png(rows, input_bytes),
        "speed_accuracy.png": charts.speed_accuracy_overall_png(rows),
    }
    for scene in input_bytes:
        made[f"rate_distortion_{scene}.png"] = charts.rate_distortion_png(rows, scene)
        made[f"speed_accuracy_{scene}.png"] = charts.speed_accuracy_png(rows, scene)
    for name, png in made.items():
        (folder / name).write_bytes(png)
    return [folder / name for name in made]


def run_bench(scenes: list[Path], out: Path, settings: BenchSettings, say: Callable[[str], None] | None = None,
              trained: Sequence[bool] | None = None) -> dict[str, Any]:  # fmt: skip
    """Bench every scene into ``out``; returns the ``bench.json`` document (also written). ``trained``: per scene,
    whether it is known to be as a trainer wrote it; the others are told trained or decoded from a quantised
    container by their own values (``kinds.container_grid``)."""
    from .tables import markdown

    say = say or (lambda message: None)
    out.mkdir(parents=True, exist_ok=True)
    names = _names(scenes)
    said = list(trained) if trained is not None else [False] * len(scenes)
    evidence = [_kind(ply, kind) for ply, kind in zip(scenes, said)]
    # Trained scenes first: they are the codec's main evidence, and the tables keep the order benched.
    order = sorted(range(len(scenes)), key=lambda i: evidence[i] is not None)
    scenes, names, evidence = [scenes[i] for i in order], [names[i] for i in order], [evidence[i] for i in order]
    kinds: list[bool | None] = [grid is None for grid in evidence]
    for name, grid in zip(names, evidence):
        say(f"{name}: " + ("as a trainer wrote it" if grid is None else f"decoded from a container ({grid})"))
    tool = None
    if settings.splat_transform is not None:
        from .splat_transform import version

        tool = version(settings.splat_transform)
    info = stamp.stamp(tool)
    rows: list[BenchRow] = []
    for ply, name, kind in zip(scenes, names, kinds):
        rows += bench_scene(ply, out, settings, say, name, kind)
    info["finished"] = stamp.stamp(tool)["date"]
    info["load_at_end"] = stamp.machine()["load"]
    doc = document(rows, scenes, names, settings, info, kinds, evidence)
    (out / "bench.json").write_text(json.dumps(doc, indent=1))
    (out / "bench.md").write_text(markdown(rows))
    write_charts(rows, {name: ply.stat().st_size for ply, name in zip(scenes, names)}, out / "charts")
    return doc
