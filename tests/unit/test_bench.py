"""The bench: our curve and sizes at equal PSNR against an exact oracle, the sweep's aim, the claims' check on
other cameras, the float16 PLY peer, and `symgs bench` end to end on a 300-Gaussian scene (bench.json's schema,
its files, its charts)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from PIL import Image

from service.cli import main
from service.cli.codec import HALF_PLY
from symgs_core.bench import curve
from symgs_core.bench.half_ply import EXTENSION, HalfPlyError, read_half_ply, write_half_ply
from symgs_core.bench.rows import REQUIRED, SCHEMA, TOLERANCE_DB, BenchRow, claims
from symgs_core.bench.run import (
    NEAR_DB,
    OURS,
    SLOPE_RANGE,
    BenchSettings,
    bench_scene,
    equal_fidelity,
    next_floor,
    other_targets,
)
from symgs_core.config import CompressConfig, budget_for_floor
from symgs_core.export import save_scene
from symgs_core.pipeline import compress, decompress
from symgs_core.synthetic import synthetic_scene


def oracle(psnr: float) -> float:
    """An exact rate-distortion curve: log bytes linear in PSNR (each dB costs 8% more bytes)."""
    return 1000.0 * math.exp(0.08 * psnr)


def test_size_at_psnr_interpolates_log_bytes_exactly_and_never_extrapolates() -> None:
    points = [(oracle(p), p) for p in (35.0, 41.0, 52.0)] + [(5e5, math.inf), (6e5, 191.8)]  # two lossless runs
    for psnr in (35.0, 38.3, 41.0, 47.9, 52.0):
        assert curve.size_at(points, psnr) == pytest.approx(oracle(psnr), rel=1e-12)
    assert curve.size_at(points, 34.9) is None and curve.size_at(points, 52.1) is None  # outside: nothing
    assert curve.size_at(points, 120.0) is None  # nothing between the lossy runs and float rounding
    assert curve.size_at(points, math.inf) is None and curve.size_at([], 40.0) is None


def test_the_curve_is_the_pareto_front() -> None:
    dominated = (oracle(45.0) * 1.5, 44.0)  # bigger and worse than the 45 dB point
    points = [(oracle(p), p) for p in (40.0, 45.0, 50.0)] + [dominated, (oracle(45.0), 45.0)]
    assert curve.front(points) == [(oracle(p), p) for p in (40.0, 45.0, 50.0)]
    assert curve.size_at(points, 44.0) == pytest.approx(oracle(44.0))  # the dominated run does not bend the curve


def test_smallest_reaching_uses_actual_points_above_the_target() -> None:
    points = [(100.0, 40.0), (200.0, 50.0), (150.0, math.inf)]  # a lossless run smaller than the 50 dB one
    assert curve.smallest_reaching(points, 30.0) == 100.0
    assert curve.smallest_reaching(points, 45.0) == pytest.approx(math.sqrt(100.0 * 200.0))
    assert curve.smallest_reaching(points, 60.0) == 150.0
    assert curve.smallest_reaching(points[:2], 60.0) is None


def test_budget_for_floor_inverts_the_self_supervised_floor() -> None:
    for floor in (38.0, 45.5, 64.6):
        budget = budget_for_floor(floor, 30.0)
        assert CompressConfig(psnr_budget=budget, nominal_psnr=30.0).self_supervised_floor() == pytest.approx(floor)


def ours(psnr: float, other: float, floor: float | None = None) -> BenchRow:
    return BenchRow("s", OURS, "sweep", "ok", "x.symgs", bytes=round(oracle(psnr)), psnr_db=psnr, psnr_other_db=other,
                    floor_db=floor)  # fmt: skip


def peer(nbytes: int, psnr: float, other: float) -> BenchRow:
    return BenchRow("s", "splat-transform spz v3", "peer", "ok", "p.spz", bytes=nbytes, psnr_db=psnr,
                    psnr_other_db=other)  # fmt: skip


def test_equal_fidelity_and_its_check_on_other_cameras() -> None:
    rows = [ours(40.0, 39.0), ours(50.0, 48.0)]
    rows += [peer(round(oracle(45.0) * 2), 45.0, 44.0),  # ours half its size; on the other rig still ahead
             peer(round(oracle(45.0) * 1.05), 45.0, 47.9),  # ours smaller here, but far behind on the other rig
             peer(round(oracle(45.0) / 2), 45.0, 44.0),  # ours twice its size: no claim
             peer(1000, 55.0, 55.0)]  # beyond our curve: not compared  # fmt: skip
    equal_fidelity(rows, "s")
    first, second, third, fourth = rows[2:]
    assert first.equal_psnr_bytes == pytest.approx(oracle(45.0), rel=1e-4)
    assert first.equal_psnr_ratio == pytest.approx(2.0, rel=1e-3)
    assert oracle(40.0) < first.equal_psnr_bytes < oracle(50.0)  # consistent with the rows it lies between
    assert first.claim_holds_other is True
    assert second.equal_psnr_ratio > 1 and second.claim_holds_other is False
    assert third.equal_psnr_ratio == pytest.approx(0.5, 1e-3) and third.claim_holds_other is None
    assert fourth.equal_psnr_bytes is None and fourth.equal_psnr_ratio is None
    made = claims(rows)
    assert [c["holds_on_other_cameras"] for c in made] == [True, False]


def test_a_claim_holds_within_the_tolerance() -> None:
    # Ours is 0.5% smaller at 45 dB. On the other rig the peer gains 0.15 dB, where ours needs 1.2% more bytes:
    # within the tolerance the claim holds; 0.3 dB would be past it.
    rows = [ours(40.0, 40.0), ours(50.0, 50.0), peer(round(oracle(45.0) * 1.005), 45.0, 45.15),
            peer(round(oracle(45.0) * 1.005), 45.0, 45.0 + TOLERANCE_DB + 0.1)]  # fmt: skip
    equal_fidelity(rows, "s")
    assert [r.claim_holds_other for r in rows[2:]] == [True, False]


def test_the_sweep_aims_past_the_targets_the_curve_does_not_span() -> None:
    rows = [ours(40.0, 40.0, floor=42.0), ours(44.0, 44.0, floor=46.0)]  # evaluation lands 2 dB under the floor
    assert next_floor(rows, "s", [43.0], []) is None  # spanned, and a run within NEAR_DB of it
    up = next_floor(rows, "s", [42.0, 60.0], [])
    assert up == pytest.approx(60.0 + 2.0 + 0.5)
    assert next_floor(rows, "s", [60.0], [up]) == pytest.approx(up + 1.0)  # never the same floor twice
    assert next_floor(rows, "s", [30.0], []) == pytest.approx(30.0 + 2.0 - 0.5)


def test_the_sweep_aims_at_a_claimed_peers_psnr_on_the_other_rig() -> None:
    """Our runs lose 3 dB on the other rig where the peer gains half a dB: the claim at 45 dB cannot be checked
    until a run of ours reaches the peer's other-rig PSNR (less the tolerance) there, so the sweep aims at it, from
    the offset of the run that landed nearest."""
    rows = [ours(40.0, 37.0, floor=40.0), ours(45.0, 42.0, floor=45.0), ours(50.0, 47.0, floor=50.0)]
    claimed = peer(round(oracle(45.0) * 2), 45.0, 48.5)
    beaten = peer(round(oracle(45.0) / 2), 45.0, 60.0)  # ours is larger here: no claim, nothing to check
    rows += [claimed, beaten]
    assert other_targets(rows, "s", OURS) == [pytest.approx(48.5 - TOLERANCE_DB)]
    assert next_floor(rows, "s", [45.0], []) is None  # the evaluation rig alone is spanned
    floor = next_floor(rows, "s", [45.0], [], other=other_targets(rows, "s", OURS))
    assert floor == pytest.approx(48.5 - TOLERANCE_DB + 3.0 + 0.5)
    rows.append(ours(52.0, 49.0, floor=floor))
    assert next_floor(rows, "s", [45.0], [floor], other=other_targets(rows, "s", OURS)) is None
    equal_fidelity(rows, "s")
    assert claimed.claim_holds_other is True


def test_the_sweep_ignores_where_an_unfitted_preset_landed() -> None:
    """``fast`` fits nothing: its PSNR lies 12.7 dB above its nominal floor (plant). Aiming from that offset would
    land far short of the target; the fitted run's offset is the one to aim from."""
    fast = BenchRow("s", OURS, "preset", "ok", "f.symgs", preset="fast", bytes=round(oracle(54.1)), psnr_db=54.1,
                    psnr_other_db=54.6, floor_db=41.46)  # fmt: skip
    high = BenchRow("s", OURS, "preset", "ok", "h.symgs", preset="high", bytes=round(oracle(49.2)), psnr_db=49.2,
                    psnr_other_db=47.0, floor_db=46.3)  # fmt: skip
    low = ours(38.2, 36.7, floor=35.9)
    assert next_floor([low, high, fast], "s", [58.0], []) == pytest.approx(58.0 - (49.2 - 46.3) + 0.5)


def test_the_sweep_puts_a_run_near_every_peers_psnr() -> None:
    """A peer's PSNR inside our curve but 5 dB from its every point: our size there would be interpolated across
    10 dB, so the sweep aims a run at it (no margin past it); a run that lands within NEAR_DB of it ends the aim."""
    rows = [ours(40.0, 40.0, floor=40.0), ours(50.0, 50.0, floor=50.0)]
    assert next_floor(rows, "s", [45.0], []) == pytest.approx(45.0)
    rows.append(ours(45.0 + NEAR_DB - 0.1, 45.0, floor=45.0))
    assert next_floor(rows, "s", [45.0], [45.0]) is None


def test_the_sweep_aims_along_the_slope_its_runs_landed_on() -> None:
    """Near the lossless end a higher floor buys little PSNR on the other rig (the lego: 0.33 dB a dB). Aimed at one
    dB a dB, run after run fell short of the peer's 60.72 dB there; along the slope of the two nearest runs one run
    reaches it. Two runs on a near-flat slope do not send the next floor past the slope's bound."""
    lego = [ours(60.32, 60.03, floor=57.98), ours(60.77, 60.36, floor=59.17), ours(61.04, 60.65, floor=60.04)]
    slope = (60.65 - 60.36) / (60.04 - 59.17)
    assert next_floor(lego, "s", [60.5], [], other=[60.72]) == pytest.approx(60.04 + (60.72 + 0.5 - 60.65) / slope)
    flat = [ours(50.0, 50.0, floor=50.0), ours(50.05, 50.05, floor=51.0)]
    low, _ = SLOPE_RANGE
    assert next_floor(flat, "s", [52.0], []) == pytest.approx(51.0 + (52.0 + 0.5 - 50.05) / low)


def test_the_sweep_aims_one_db_a_db_from_runs_of_other_presets_or_far_away() -> None:
    """The lego's balanced and high presets landed 0.27 dB of PSNR a dB of floor apart; along that slope a run aimed
    at float16's 60.14 dB was sent to a floor of 97 (it landed at 64 dB, 13 dB past the target it was to span).
    Runs of two presets, or far from the target, aim one dB a dB from the nearest."""

    def preset_run(preset: str, psnr: float, floor: float) -> BenchRow:
        return BenchRow("s", OURS, "preset", "ok", f"{preset}.symgs", preset=preset, bytes=round(oracle(psnr)),
                        psnr_db=psnr, psnr_other_db=psnr, floor_db=floor)  # fmt: skip

    rows = [preset_run("balanced", 45.70, 41.46), preset_run("high", 47.01, 46.33)]
    assert next_floor(rows, "s", [60.14], []) == pytest.approx(46.33 + (60.14 + 0.5 - 47.01))
    far = [ours(40.0, 40.0, floor=38.0), ours(50.0, 50.0, floor=60.0)]  # the same preset, 10 dB apart
    assert next_floor(far, "s", [55.0], []) == pytest.approx(60.0 + 5.5)


def test_half_ply_round_trip_and_refusals() -> None:
    scene = synthetic_scene("global", n=200, seed=4, sh_degree=2).scene
    data = write_half_ply(scene)
    back = read_half_ply(data)
    for name, value in scene.tensors().items():
        assert torch.equal(back.tensors()[name], value.half().float()), name
    assert EXTENSION == HALF_PLY  # the CLI names the extension without importing the bench
    import zstandard

    ply = zstandard.ZstdDecompressor().decompress(data)
    for bad, match in [
        (b"not zstd", "zstd"),
        (zstandard.ZstdCompressor().compress(ply[:-2]), "need"),
        (zstandard.ZstdCompressor().compress(ply.replace(b"half x", b"half q")), "graphdeco"),
    ]:
        with pytest.raises(HalfPlyError, match=match):
            read_half_ply(bad)


def test_bench_writes_bench_json_files_and_charts(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SYMGS_NPM_CACHE", str(tmp_path / "no-npm"))  # splat-transform absent: its peers unavailable
    monkeypatch.delenv("SPLAT_TRANSFORM", raising=False)
    save_scene(synthetic_scene("global", n=300, seed=1, sh_degree=1).scene, tmp_path / "tiny.ply")
    out = tmp_path / "out"
    tiny = ["--iterations", "2", "--max-levels", "1", "--train-views", "2", "--fit-views", "2", "--eval-views", "2",
            "--resolution", "24", "--eval-resolution", "24", "--other-views", "2"]  # fmt: skip
    code = main(["bench", str(tmp_path / "tiny.ply"), "--out", str(out), "--presets", "balanced", "--mirrors", "off",
                 "--sweep", "1", "--no-install", "--trained", str(tmp_path / "tiny.ply"), *tiny])  # fmt: skip
    assert code == 0
    doc = json.loads((out / "bench.json").read_text())
    assert doc["schema"] == SCHEMA and doc["generated"]["machine"]["cores"] >= 1 and doc["generated"]["commit"]
    rows = [BenchRow.from_json(r) for r in doc["rows"]]
    assert all(set(REQUIRED) <= set(r) for r in doc["rows"])
    by_method = {r.method: r for r in rows if r.role != "sweep"}
    assert by_method["splat-transform spz v3"].status == "unavailable"
    assert "not installed" in by_method["splat-transform spz v3"].reason
    half, mine = by_method["float16 ply + zstd"], by_method["symgs no mirrors"]
    assert half.ok and mine.ok and mine.preset == "balanced" and mine.mirrors is False
    ply_bytes = (tmp_path / "tiny.ply").stat().st_size
    for r in (row for row in rows if row.ok):
        assert (out / r.file).stat().st_size == r.bytes and r.ratio == pytest.approx(ply_bytes / r.bytes)
        assert r.psnr_db > 20 and r.psnr_other_db > 20 and 0 < r.ssim <= 1 and r.encode_s > 0 and r.decode_s >= 0
    sweep = [r for r in rows if r.role == "sweep"]
    assert len(sweep) == 1 and sweep[0].method == "symgs no mirrors"  # mirrors off: the curve is the plain codec
    assert decompress((out / mine.file).read_bytes()).means.shape == (mine.gaussians, 3)
    assert main(["decompress", str(out / half.file), "-o", str(tmp_path / "half.ply")]) == 0
    assert doc["cameras"]["evaluation"]["seed"] != doc["cameras"]["other"]["seed"]
    for name, size in [
        ("rate_distortion.png", (1000, 600)),
        ("speed_accuracy.png", (1000, 600)),
        ("rate_distortion_tiny.png", (900, 520)),
        ("speed_accuracy_tiny.png", (900, 520)),
    ]:
        with Image.open(out / "charts" / name) as image:
            assert image.format == "PNG" and image.size == size, name
    tables = (out / "bench.md").read_text()
    assert "| tiny | float16 ply + zstd |" in tables and "| tiny | symgs no mirrors | balanced |" in tables
    assert sum(mine.sections.values()) == mine.bytes and f"| tiny | {mine.bytes:,} |" in tables
    assert all(r.trained for r in rows) and doc["scenes"][0]["trained"] is True
    assert "| float16 ply + zstd | trained |" in tables  # the summary reports trained scenes apart


def test_a_rows_psnr_is_the_one_its_report_states(tmp_path: Path) -> None:
    """The bench's evaluation rig is the pipeline's own evaluation cameras (which fitted nothing)."""
    ply = tmp_path / "tiny.ply"
    save_scene(synthetic_scene("global", n=200, seed=5, sh_degree=1).scene, ply)
    tiny = {"iterations": 2, "max_levels": 1, "train_views": 2, "fit_views": 2, "eval_views": 3, "resolution": 24,
            "eval_resolution": 24, "device": "cpu"}  # fmt: skip
    settings = BenchSettings(presets=("small",), mirrors=(False,), overrides=tiny, peers=(), sweep=0, other_views=2)
    (row,) = bench_scene(ply, tmp_path / "out", settings)
    report = compress(ply, config=settings.config("small", use_mirrors=False)).report
    assert row.bytes == report.output_bytes and row.floor_db == pytest.approx(report.psnr_floor)
    assert row.psnr_db == pytest.approx(report.fidelity.psnr, abs=1e-6)
    assert row.psnr_object_db == pytest.approx(report.fidelity.psnr_object, abs=1e-6)
    assert row.psnr_other_db != pytest.approx(row.psnr_db, abs=1e-6)  # another rig: other cameras


def test_bench_refuses_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", str(tmp_path / "missing.ply"), "--out", str(tmp_path)]) == 2
    save_scene(synthetic_scene("global", n=50, seed=1).scene, tmp_path / "s.ply")
    assert main(["bench", str(tmp_path / "s.ply"), "--out", str(tmp_path), "--presets", "tiny"]) == 2
    assert main(["bench", str(tmp_path / "s.ply"), "--out", str(tmp_path), "--sweep", "-1"]) == 2
    assert "unknown presets" in capsys.readouterr().err


def test_a_float32_run_reaches_every_psnr_but_is_no_point_of_the_curve() -> None:
    """The lossless preset's renders differ by float rounding only, at whatever PSNR that measures (73 dB on one real
    scene): a peer between our finest lossy run and it is not spanned, so the sweep aims at it."""
    lossless = BenchRow("s", OURS, "preset", "ok", "l.symgs", preset="lossless", bytes=round(oracle(90.0)),
                        psnr_db=73.0, psnr_other_db=75.0)  # fmt: skip
    rows = [ours(40.0, 40.0, floor=40.0), ours(50.0, 50.0, floor=50.0), lossless]
    assert next_floor(rows, "s", [60.0], []) == pytest.approx(60.5)
    peer_row = peer(round(oracle(60.0)), 60.0, 60.0)
    equal_fidelity([*rows, peer_row], "s")
    assert peer_row.equal_psnr_bytes is None and peer_row.claim_holds_other is None
