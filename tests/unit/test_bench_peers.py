"""The peers as PlayCanvas splat-transform (the pinned version) writes and reads them: in a bench, with our size at
their PSNR; on a job's upload, in its charts. Skips, with the reason, without Node.js/npm or when the package
cannot be installed."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from symgs_core.bench import splat_transform
from symgs_core.bench.peers import PEERS, run_peers
from symgs_core.bench.run import OURS_PLAIN, BenchSettings, bench_scene
from symgs_core.config import CompressConfig
from symgs_core.export import save_scene
from symgs_core.pictures import job_charts
from symgs_core.pipeline import compress
from symgs_core.ply import load_scene
from symgs_core.report import Report
from symgs_core.synthetic import synthetic_scene
from tests.unit.test_pictures import png
from worker.peers import upload_peers

TINY = {"iterations": 2, "max_levels": 1, "train_views": 2, "fit_views": 2, "eval_views": 2, "resolution": 24,
        "eval_resolution": 24, "device": "cpu"}  # fmt: skip


@pytest.fixture(scope="module")
def exe() -> str:
    try:
        return splat_transform.install()
    except splat_transform.ToolError as exc:
        pytest.skip(str(exc))


@pytest.fixture(scope="module")
def ply(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("peers") / "tiny.ply"
    save_scene(synthetic_scene("global", n=300, seed=1, sh_degree=1).scene, path)
    return path


@pytest.fixture(scope="module")
def report(ply: Path) -> Report:
    return compress(ply, config=CompressConfig.for_preset("balanced", use_mirrors=False, **TINY)).report


def test_the_pinned_version_runs(exe: str) -> None:
    assert splat_transform.version(exe) == splat_transform.VERSION or "SPLAT_TRANSFORM" in os.environ


def test_every_peer_writes_a_file_its_tool_reads_back(exe: str, ply: Path, tmp_path: Path) -> None:
    source = load_scene(ply)
    found = run_peers(ply, source, tmp_path, exe=exe, timeout=120)
    assert [f.peer for f in found] == list(PEERS)
    for f in found:
        assert f.status == "ok", (f.peer.method, f.reason)
        assert f.path is not None and f.path.stat().st_size == f.bytes and len(f.decoded) == len(source)
    limited = run_peers(ply, load_scene(ply), tmp_path, exe=exe, timeout=120, peers=PEERS[3:4], slow_timeout=0.01)
    assert limited[0].status == "timed_out" and not (tmp_path / PEERS[3].file).exists()


def test_spz_v3_carries_our_size_at_its_psnr(exe: str, ply: Path, tmp_path: Path) -> None:
    settings = BenchSettings(presets=("balanced",), mirrors=(False,), overrides=TINY, peers=PEERS[:1],
                             splat_transform=exe, sweep=4, other_views=2)  # fmt: skip
    rows = bench_scene(ply, tmp_path, settings)
    spz = rows[0]
    assert spz.method == "splat-transform spz v3" and spz.ok
    ours = sorted((r for r in rows if r.method == OURS_PLAIN), key=lambda r: r.psnr_db)
    assert ours[0].psnr_db <= spz.psnr_db <= ours[-1].psnr_db, [r.psnr_db for r in ours]  # the sweep spans it
    assert spz.equal_psnr_ratio == pytest.approx(spz.bytes / spz.equal_psnr_bytes)
    below = max((r for r in ours if r.psnr_db <= spz.psnr_db), key=lambda r: r.psnr_db)
    above = min((r for r in ours if r.psnr_db >= spz.psnr_db), key=lambda r: r.psnr_db)
    assert min(below.bytes, above.bytes) <= spz.equal_psnr_bytes <= max(below.bytes, above.bytes)
    assert (spz.claim_holds_other is None) == (spz.equal_psnr_ratio <= 1)


def test_a_job_draws_the_peers_in_its_charts(exe: str, ply: Path, report: Report, tmp_path: Path) -> None:
    peers = upload_peers(ply, None, report, seconds=120, work=tmp_path)
    assert peers
    charts = job_charts(report, peers=peers)
    assert set(charts) == {"rate_distortion", "speed_accuracy"} and charts != job_charts(report)
    assert all(png(data).size == (820, 420) for data in charts.values())
    assert upload_peers(ply, None, report, seconds=0, work=tmp_path) == []  # turned off


def test_without_the_tool_a_job_keeps_its_own_charts(ply: Path, report: Report, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    monkeypatch.setenv("SYMGS_NPM_CACHE", str(tmp_path / "no-npm"))
    monkeypatch.delenv("SPLAT_TRANSFORM", raising=False)
    assert upload_peers(ply, None, report, seconds=60, work=tmp_path) == []
