"""The codec bench on scenes as trainers write them first, then on scenes decoded from quantised containers.

    python benchmarks/bench_codec.py --captures ../shared/data/nerf_synthetic_lego_400px \
        --scenes ../shared/data/kacytran_try_iter7000/point_cloud.ply ../shared/data/fox_cc0_mujoco_warp/fox.ply \
        --work bench-out/pipeline-capture --out bench-out/codec -- --device cpu

Uploads from a trainer hold float32 values on no grid; most shared scenes were decoded from SOG, `.spz`, `.splat` or
compressed PLY, whose values sit on grids those formats re-encode almost losslessly. So the trained scenes come first
and the two kinds are reported apart: the scenes trained here from the photographs of each ``--captures`` folder
(``symgs_core.bench.capture``, trained once and read from ``--work`` after, as the pipeline-capture bench does;
``symgs bench --trained``), then the ``--scenes``, each told by its own values (``symgs_core.bench.kinds``). Every
argument after ``--`` goes to ``symgs bench``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    from service.cli import main as cli
    from symgs_core.bench.capture import cached_capture
    from symgs_core.datasets import DatasetError

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--captures", nargs="*", default=[], type=Path, help="photograph folders to train scenes from")
    parser.add_argument("--scenes", nargs="*", default=[], type=Path, help="scenes (.ply)")
    parser.add_argument("--work", type=Path, required=True, help="where the captures' trained scenes are kept")
    parser.add_argument("--out", type=Path, required=True)
    args, rest = parser.parse_known_args()
    rest = [a for a in rest if a != "--"]
    trained = []
    for folder in args.captures:
        try:
            ply = cached_capture(folder, args.work / folder.name,
                                 say=lambda m, f=folder: print(f"{f.name}: {m}", flush=True))  # fmt: skip
        except DatasetError as exc:  # photographs this build cannot read: said, not fatal
            print(f"{folder.name}: not trained, left out: {exc}", flush=True)
            continue
        # The bench names a scene by its file: a link named after the capture, not after the cache's key.
        named = args.out / "captures" / f"{folder.name}.ply"
        named.parent.mkdir(parents=True, exist_ok=True)
        named.unlink(missing_ok=True)
        named.symlink_to(ply.resolve())
        trained.append(named)
    scenes = [str(p) for p in [*trained, *args.scenes]]
    return cli(["bench", *scenes, "--out", str(args.out), "--trained", *map(str, trained), *rest])


if __name__ == "__main__":
    raise SystemExit(main())
