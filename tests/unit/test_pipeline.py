"""End-to-end compress/decompress on small generated scenes: levels pay for themselves or are rolled back."""

from __future__ import annotations

import functools
import gc
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from symgs_core.bench.photos import photographed
from symgs_core.config import CompressConfig
from symgs_core.detect import DetectConfig, detect
from symgs_core.pipeline import compress, decompress, result
from symgs_core.pipeline.budget import RateDistortion
from symgs_core.pipeline.encode import Fitted, Rate
from symgs_core.pipeline.job import Reporter, stage_shares
from symgs_core.pipeline.levels import SETTLED_COST, LevelSearch, memberships, run_levels
from symgs_core.pipeline.state import LevelState
from symgs_core.progress import Cancelled
from symgs_core.scene import GaussianScene
from symgs_core.synthetic import synthetic_scene
from symgs_core.views import dataset_views, evaluate, self_supervised_views

# Float32 attributes: what is left to judge is the mirrors alone, with half a decibel to spend.
FAST = CompressConfig.for_preset(
    "lossless", psnr_budget=0.5, iterations=10, train_views=4, fit_views=2, eval_views=2, resolution=64,
    eval_resolution=64, max_levels=2, pictures=False,
)


def _archive_of(size: int) -> Fitted:
    """A judged archive of ``size`` bytes, for a judge that prices levels without encoding them."""
    return Fitted(LevelState.plain(GaussianScene.empty(0)), bytes(size), math.inf, None)


def _levels(scene, views, config, judge, *, floor, reference=math.inf, rate=None):  # noqa: ANN001, ANN202
    search = LevelSearch(scene, views, floor, reference, 1.0, 10_000, None, rate)
    outcome = run_levels(search, config=config, judge=judge, report=Reporter(None, None), checkpoint=None)
    return outcome.state, outcome.psnr, outcome.records


@pytest.fixture(scope="module")
def symmetric():
    """Exact twins whose attributes carry a little independent jitter, as two captured halves would: bit-identical
    twins would let the baseline's entropy coder find the duplicates and understate what mirrors save."""
    planted = synthetic_scene("global", n=1500, seed=3, sh_degree=1)
    s, gen = planted.scene, torch.Generator().manual_seed(0)
    jitter = lambda t: t + 1e-3 * torch.randn(t.shape, generator=gen)  # noqa: E731
    planted.scene = s.with_(
        scales=jitter(s.scales), opacities=jitter(s.opacities), sh_dc=jitter(s.sh_dc), sh_rest=jitter(s.sh_rest)
    )
    return planted


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    return tmp_path_factory.mktemp("checkpoints")


@pytest.fixture(scope="module")
def symmetric_result(symmetric, checkpoints):
    return compress(symmetric.scene, config=FAST, checkpoint_dir=checkpoints)


def test_symmetric_scene_halves_the_archive_at_high_fidelity(symmetric, symmetric_result):
    report = symmetric_result.report
    accepted = report.accepted_levels
    assert len(accepted) >= 1
    first = accepted[0]
    angle = math.degrees(
        math.acos(min(1.0, abs(sum(a * b for a, b in zip(first.normal, symmetric.planes[0].normal)))))
    )
    assert angle < 1.0
    assert report.ratio_to_baseline >= 1.6
    assert report.gaussians.stored <= 0.55 * report.gaussians.input
    assert report.gaussians.decoded >= report.gaussians.input * 0.95
    assert report.fitting.worst >= report.psnr_floor >= 39.0
    assert report.cameras.disjoint and report.cameras.evaluation.name == "evaluation"
    assert report.cameras.background == (0.0, 0.0, 0.0)  # renders of the input are drawn on black
    assert report.cameras.photographs is None


def test_decoded_archive_is_the_scene_that_was_judged(symmetric, symmetric_result):
    decoded = decompress(symmetric_result.archive)
    assert len(decoded) == symmetric_result.report.gaussians.decoded
    views = self_supervised_views(
        symmetric.scene, train=FAST.train_views, fit=FAST.fit_views, eval=FAST.eval_views,
        resolution=FAST.resolution, eval_resolution=FAST.eval_resolution, background=torch.zeros(3),
    )  # fmt: skip
    fidelity = evaluate(decoded, views.eval, views.background)
    assert fidelity == symmetric_result.report.fidelity
    assert evaluate(decoded, views.fit, views.background) == symmetric_result.report.fitting
    assert decompress(symmetric_result.archive).means.equal(decoded.means)  # decoding is deterministic


def test_asymmetric_scene_gets_no_level_and_is_no_larger_than_baseline():
    scene = synthetic_scene("asymmetric", n=1500, seed=5).scene
    result = compress(scene, config=FAST)
    report = result.report
    assert not report.accepted_levels and report.notes == ()  # no mirror found: nothing to advise
    assert report.gaussians.stored == len(scene)
    assert report.output_bytes <= 1.02 * report.baseline_bytes
    # Lossless: the decoded scene is the input, reordered for coding.
    decoded = decompress(result.archive)
    rows = lambda s: torch.cat([t.reshape(len(s), -1) for t in s.tensors().values()], dim=1)  # noqa: E731
    order = lambda r: r[torch.argsort(r[:, 0] * 1e6 + r[:, 1])]  # noqa: E731
    assert torch.equal(order(rows(decoded)), order(rows(scene)))


def test_a_level_is_kept_only_when_the_archive_with_it_is_smaller(symmetric):
    """The judge prices each level by its whole archive at the floor: a level that holds the floor but does not make
    the archive smaller than the best so far is rolled back, and the search stops there."""
    scene = symmetric.scene
    views = self_supervised_views(scene, train=4, fit=2, eval=2, resolution=48, eval_resolution=48,
                                  background=torch.zeros(3))  # fmt: skip
    config = replace(FAST, max_levels=2, iterations=4)
    judged = []

    def run(bytes_of):  # noqa: ANN001, ANN202
        judge = lambda st, p, _: judged.append(len(st.stored)) or _archive_of(bytes_of(st))  # noqa: E731
        return _levels(scene, views, config, judge, floor=30.0)

    state, psnr, records = run(lambda st: 10_000)  # no smaller than the plain codec's
    assert judged and state.normals.shape[0] == 0 and math.isinf(psnr)
    assert records and not records[0].accepted and "not smaller" in records[0].reason
    assert records[0].archive_bytes == 10_000
    state, _, records = run(lambda st: 9_000 - st.normals.shape[0])  # each level shrinks it
    assert records[0].accepted and state.normals.shape[0] >= 1 and "shrinks" in records[0].reason


def test_the_levels_move_the_bar_through_each_fine_tune_and_its_encode(symmetric):
    """The progress bar passes through each level's fine-tune, then the encode that judges it (the judge's own
    progress), and the first level fills half of the levels' share: a job's time left follows every part of it."""
    scene = symmetric.scene
    views = self_supervised_views(scene, train=4, fit=2, eval=2, resolution=48, eval_resolution=48,
                                  background=torch.zeros(3))  # fmt: skip
    config = replace(FAST, max_levels=2, iterations=20)
    shares = stage_shares(config, photographs=False)
    events = []

    def judge(state, psnr, progress):  # noqa: ANN001, ANN202
        progress(0.5, "half way")
        return _archive_of(9_000 - state.normals.shape[0])  # each level shrinks it

    search = LevelSearch(scene, views, 30.0, math.inf, 1.0, 10_000, None, None)
    outcome = run_levels(search, config=config, judge=judge, report=Reporter(events.append, None, shares),
                         checkpoint=None)  # fmt: skip
    assert [r.accepted for r in outcome.records][:1] == [True]
    lo, hi = shares["levels"]
    at = {e.message: e.fraction for e in events}
    fractions = [e.fraction for e in events]
    assert fractions == sorted(fractions) and lo <= fractions[0] and fractions[-1] == pytest.approx(hi)
    assert at["level 0: detecting mirrors"] == pytest.approx(lo)
    steps = [e.fraction for e in events if e.message.startswith("level 0: step")]
    assert steps and at["level 0: detecting mirrors"] <= steps[0] <= steps[-1] < at["level 0: encoding to compare"]
    assert at["level 0: encoding to compare"] < at["level 0: encoding to compare: half way"] < (lo + hi) / 2
    assert at["level 1: detecting mirrors"] == pytest.approx((lo + hi) / 2)


def test_a_membership_the_rate_model_says_cannot_pay_is_neither_fine_tuned_nor_judged(symmetric):
    """The rate model prices the budget a membership spends: where even a fine-tune's gain would leave the codec too
    little to beat the best archive, the minutes of fine-tune and judge are not spent, and the report says why."""
    scene = symmetric.scene
    views = self_supervised_views(scene, train=4, fit=2, eval=2, resolution=48, eval_resolution=48,
                                  background=torch.zeros(3))  # fmt: skip
    config = replace(FAST, max_levels=1, iterations=4)
    judged, priced = [], []

    def run(ratio):  # noqa: ANN001, ANN202
        return _levels(scene, views, config, lambda st, p, _: judged.append(p) or _archive_of(9_000), floor=30.0,
                       rate=Rate(lambda before, after: priced.append((before, after)) or ratio))

    state, _, records = run(3.0)  # a third of the scene dropped, three times the bytes per Gaussian: no
    assert priced and all(math.isinf(before) for before, _ in priced)
    assert not judged and state.normals.shape[0] == 0
    assert records and all(r.iterations == 0 and not r.accepted and "predicted at" in r.reason for r in records)
    state, _, records = run(1.0)
    assert judged and records[0].accepted and state.normals.shape[0] == 1


def test_a_membership_that_costs_the_codec_almost_nothing_is_judged_without_a_fine_tune(symmetric):
    """Against renders of the input a fine-tune can save at most what a membership costs the codec as it starts: one
    priced under ``SETTLED_COST`` of the bytes (near-exact twins) is judged as it is, and the steps go to one that
    costs more. Against photographs (a finite reference) a fine-tune may gain beyond the input: it always runs."""
    scene = symmetric.scene
    views = self_supervised_views(scene, train=4, fit=2, eval=2, resolution=48, eval_resolution=48,
                                  background=torch.zeros(3))  # fmt: skip
    config = replace(FAST, max_levels=1, iterations=4)

    def run(cost, reference=math.inf):  # noqa: ANN001, ANN202
        return _levels(scene, views, config, lambda st, p, _: _archive_of(9_000), floor=20.0, reference=reference,
                       rate=Rate(lambda before, after: 1.0 + cost))

    _, _, records = run(SETTLED_COST / 2)
    assert records[0].accepted and records[0].iterations == 0
    assert records[0].psnr_after == records[0].psnr_before and "not fine-tuned" in records[0].reason
    for cost, reference in ((SETTLED_COST * 10, math.inf), (SETTLED_COST / 2, 60.0)):
        _, _, records = run(cost, reference)
        assert records[0].accepted and records[0].iterations > 0 and "not fine-tuned" not in records[0].reason


def test_colour_gates_keep_asymmetric_details_out_of_a_level(symmetric):
    """A patch repainted on the right side only: the gated membership keeps it, the geometric one drops it."""
    scene = symmetric.scene.clone()
    right = symmetric.right[0]
    patch = right[scene.means[right, 1] > scene.means[right, 1].quantile(0.8)]
    scene.sh_dc[patch] = torch.tensor([3.0, -3.0, -3.0])  # saturated red where the left side is not
    mirror = detect(scene, DetectConfig(max_mirrors=1))[0]
    options = memberships(LevelState.plain(scene), mirror)
    assert options[0].gate is None and any(o.gate is not None for o in options)
    loosest = options[1]
    kept = set(patch.tolist()) - set(loosest.right.tolist())
    assert len(kept) >= 0.9 * len(patch)  # the repainted patch is no longer dropped
    assert loosest.right.numel() >= 0.7 * options[0].right.numel()  # the rest of the mirror still is


def test_zero_budget_keeps_the_plain_codec(symmetric):
    report = compress(symmetric.scene, config=replace(FAST, psnr_budget=0.0)).report
    assert report.levels and not report.levels[0].accepted
    assert report.gaussians.stored == len(symmetric.scene)
    assert report.output_bytes == report.baseline_bytes


def test_checkpoint_resume_gives_the_same_archive_without_recomputing(symmetric, symmetric_result, checkpoints):
    assert "optimize" in symmetric_result.report.seconds
    again = compress(symmetric.scene, config=FAST, checkpoint_dir=checkpoints)
    assert again.archive == symmetric_result.archive
    assert "optimize" not in again.report.seconds and "detect" not in again.report.seconds
    uninterrupted = compress(symmetric.scene, config=FAST)
    assert uninterrupted.archive == symmetric_result.archive


def test_checkpoint_of_other_inputs_is_never_trusted(symmetric, checkpoints, tmp_path):
    (tmp_path / "levels.pt").write_bytes((checkpoints / "levels.pt").read_bytes())
    other = compress(symmetric.scene, config=replace(FAST, max_levels=1), checkpoint_dir=tmp_path)
    assert "detect" in other.report.seconds


def test_progress_is_monotone_and_cancel_stops(symmetric):
    events = []
    compress(symmetric.scene, config=replace(FAST, max_levels=1), progress=events.append)
    fractions = [e.fraction for e in events]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    # A quantised preset runs the reductions and the step fit twice (with the mirrors, then without): still monotone.
    quantised = []
    config = replace(FAST, max_levels=1, preset="small", psnr_budget=3.0)
    result = compress(symmetric.scene, config=config, progress=quantised.append)
    fractions = [e.fraction for e in quantised]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert result.report.plain_codec_bytes is not None  # the second pass ran
    assert {"load", "views", "levels", "encode", "evaluate"} <= {e.stage for e in events}
    calls = iter(range(1000))
    with pytest.raises(Cancelled):
        compress(symmetric.scene, config=FAST, should_stop=lambda: next(calls) > 5)


def test_quantised_result_is_never_larger_than_the_plain_codec(symmetric):
    report = compress(symmetric.scene, config=replace(FAST, preset="balanced", psnr_budget=None)).report
    assert report.codec.name == "balanced" and report.config.budget == 0.3
    if report.accepted_levels:
        assert report.plain_codec_bytes is not None
        assert report.output_bytes < report.plain_codec_bytes
    else:  # mirrors were refused or did not pay: the result is the plain codec's
        assert report.gaussians.decoded == report.gaussians.stored
    assert report.fitting.worst >= report.psnr_floor - 1e-6


def test_the_report_accounts_for_every_stage_and_keeps_the_floor() -> None:
    scene = synthetic_scene("global", n=900, seed=6, sh_degree=1).scene
    config = replace(FAST, preset="balanced", psnr_budget=None, max_levels=1)
    result = compress(scene, config=config)
    report = result.report
    stages = report.stages
    assert [s.stage for s in stages] == ["mirrors", "quantization", "pruning", "sh_reduction"]
    for before, after in zip(stages, stages[1:]):
        assert after.bytes_before == before.bytes_after
    assert stages[-1].bytes_after == len(result.archive) == report.output_bytes
    assert sum(part.bytes for part in report.sections) == report.output_bytes
    index = "sh_index" if report.codec.steps and report.codec.steps.sh_palette else "sh_degrees"
    assert [part.name for part in report.sections][-4:] == [index, "sh_band_1", "bits", "classes"]
    assert report.fitting.worst >= report.psnr_floor == pytest.approx(config.self_supervised_floor())
    assert stages[-1].psnr_after == pytest.approx(report.fitting.worst) and not stages[-1].predicted
    assert stages[1].predicted
    if not report.accepted_levels:  # what pruning removed is what the archive stores fewer of
        assert stages[2].removed == report.gaussians.input - report.gaussians.stored
    lossless = compress(scene, config=replace(config, preset="lossless", psnr_budget=0.0)).report
    assert report.output_bytes * 4 < lossless.output_bytes
    assert len(decompress(result.archive)) == report.gaussians.decoded


def test_a_job_changes_no_process_wide_state(symmetric):
    """Two jobs of different steps in one process: the codec registry is what the imports made it."""
    from symgs_core.codec import registry

    before = (dict(registry._SECTION_CODECS), dict(registry._ARCHIVE_CODECS))
    for budget in (3.0, 1.0):
        compress(symmetric.scene, config=replace(FAST, preset="small", psnr_budget=budget, max_levels=0))
    assert (dict(registry._SECTION_CODECS), dict(registry._ARCHIVE_CODECS)) == before


def test_a_resumed_job_recognises_its_dataset_wherever_it_lies(tmp_path) -> None:  # noqa: ANN001
    from symgs_core.pipeline.checkpoint import settings_digest

    config = CompressConfig.for_preset()
    here, there = tmp_path / "host_a" / "data", tmp_path / "host_b" / "elsewhere"
    for root in (here, there):
        (root / "images").mkdir(parents=True)
        (root / "images" / "r_0.png").write_bytes(b"\x89PNG pixels")
        (root / "transforms_train.json").write_text('{"frames": []}')
    assert settings_digest(config, here) == settings_digest(config, there)
    (there / "images" / "r_0.png").write_bytes(b"\x89PNG other pixels")
    assert settings_digest(config, here) != settings_digest(config, there)


def test_the_fast_preset_encodes_once_at_fixed_steps_and_reports_what_it_measured() -> None:
    scene = synthetic_scene("global", n=600, seed=3, sh_degree=1).scene
    config = CompressConfig.for_preset("fast", resolution=32, eval_resolution=32, pictures=False, device="cpu")
    assert (config.max_levels, config.fit_views, config.eval_views) == (0, 2, 4)  # the preset's own defaults
    assert CompressConfig.for_preset("fast", eval_views=3).eval_views == 3  # a caller's value wins
    result = compress(scene, config=config)
    report = result.report
    assert report.levels == () and [s.stage for s in report.stages] == ["mirrors", "entropy_coding"]
    assert report.codec.floor is None and report.codec.steps is not None and report.codec.tries == 0
    decoded = decompress(result.archive)
    assert len(decoded) == len(scene) == report.gaussians.decoded  # nothing pruned
    assert math.isfinite(report.fidelity.psnr) and report.stages[-1].psnr_after == pytest.approx(report.fitting.worst)


def _rate_models_alive() -> int:
    gc.collect()
    return sum(type(o) is RateDistortion for o in gc.get_objects())


def test_against_photographs_a_capture_like_scene_keeps_its_mirror_and_shrinks(tmp_path, monkeypatch):
    """The paper's protocol: fidelity against photographs of a symmetric object, the upload's mirrored half an
    independent reconstruction of it. Reflected, the kept half renders the photographs about as well as the half it
    replaces, so the level spends little of the budget and the archive shrinks, at no lower test-photo PSNR. No rate
    model (about 1 GB at 1M Gaussians with SH 3) is alive while the report's own archives are written: not the
    upload's, the fine-tuned scene's nor the level's."""
    upload = photographed("global", tmp_path, n=1500, photos=16, tests=4, resolution=64)
    config = CompressConfig.for_preset("balanced", iterations=20, fit_views=4, eval_views=4, eval_resolution=64,
                                       max_levels=1, device="cpu", pictures=False)  # fmt: skip
    alive, stages = [], result.stages
    monkeypatch.setattr(result, "stages", lambda *a, **k: alive.append(_rate_models_alive()) or stages(*a, **k))
    mirrored = compress(upload, images=tmp_path, config=config).report
    assert alive == [0] and mirrored.refinement is not None
    plain = compress(upload, images=tmp_path, config=replace(config, use_mirrors=False)).report
    assert mirrored.cameras.evaluation.source == "photographs"
    read = mirrored.cameras.photographs
    assert read is not None and (read.width, read.height, read.scale) == (64, 64, 1.0)  # judged at their own size
    assert mirrored.accepted_levels and mirrored.fitting.worst >= mirrored.psnr_floor
    # Judged at the plain archive's own fidelity, above the floor: the mirror is kept for being smaller, not for
    # spending fidelity the plain codec could not.
    assert plain.fitting.worst > plain.psnr_floor
    assert mirrored.psnr_mirror_floor == pytest.approx(plain.fitting.worst)
    assert mirrored.fitting.worst >= plain.fitting.worst
    assert mirrored.output_bytes < 0.8 * plain.output_bytes
    assert mirrored.fidelity.worst >= plain.fidelity.worst - 0.1
    assert mirrored.notes == ()
    # The same upload without its photographs: against its own renders the mirror does not pay, and the report
    # says what would make it.
    alone = compress(upload, config=config).report
    assert not alone.accepted_levels and alone.levels
    (note,) = alone.notes
    assert "no mirror level paid against renders of the upload" in note and "--images" in note


def test_a_mirror_is_held_to_the_plain_archives_fidelity_where_that_lies_above_the_floor(tmp_path):
    """With a budget wider than the plain codec's coarsest steps can spend, its archive lands above the floor; a
    mirror judged at the floor could then be smaller only for being worse. Against photographs it is held to the
    plain archive's own fitting PSNR instead, and still pays; a job resumed after its levels codes them held alike,
    to the very bytes of the uninterrupted run."""
    shots, checkpoints = tmp_path / "shots", tmp_path / "checkpoints"
    upload = photographed("global", shots, n=1500, photos=16, tests=4, resolution=64)
    config = CompressConfig.for_preset("balanced", psnr_budget=6.0, iterations=20, fit_views=4, eval_views=4,
                                       eval_resolution=64, max_levels=1, device="cpu", pictures=False)  # fmt: skip
    mirrored = compress(upload, images=shots, config=config).report
    plain = compress(upload, images=shots, config=replace(config, use_mirrors=False)).report
    assert plain.fitting.worst > plain.psnr_floor + 0.3 and plain.psnr_mirror_floor is None
    assert mirrored.psnr_mirror_floor == pytest.approx(plain.fitting.worst)
    assert all(level.psnr_after >= mirrored.psnr_mirror_floor for level in mirrored.accepted_levels)
    assert mirrored.accepted_levels and mirrored.fitting.worst >= plain.fitting.worst
    assert mirrored.output_bytes < plain.output_bytes and mirrored.fidelity.worst >= plain.fidelity.worst - 0.1
    # At a budget of 1 dB the held PSNR binds the mirrored archive's steps (coded at the floor they would differ).
    config = replace(config, psnr_budget=1.0)
    first = compress(upload, images=shots, config=config, checkpoint_dir=checkpoints)
    assert first.report.accepted_levels and first.report.psnr_mirror_floor > first.report.psnr_floor
    again = compress(upload, images=shots, config=config, checkpoint_dir=checkpoints)
    assert "detect" not in again.report.seconds and again.archive == first.archive


def test_against_its_own_renders_a_mirror_is_held_to_the_floor_alone(symmetric):
    """Without photographs both archives are fitted to one floor and land above it by the same search's margin: the
    levels hold the floor, not the plain archive's landing as well."""
    report = compress(symmetric.scene, config=replace(FAST, preset="small", psnr_budget=3.0, max_levels=1)).report
    assert report.levels and report.psnr_mirror_floor == report.psnr_floor


def test_a_scene_in_tiny_units_is_seen_and_compressed_as_at_its_own_size():
    """Cameras placed around a scene bring their near plane along: a scene a million times smaller renders the same
    images, not blank ones that any archive would match "losslessly"."""
    scene = synthetic_scene("global", n=600, seed=1, sh_degree=0).scene
    tiny = scene.with_(means=scene.means * 1e-6, scales=scene.scales + math.log(1e-6))
    sets = [self_supervised_views(s, train=0, fit=3, eval=0, resolution=32, eval_resolution=32,
                                  background=torch.zeros(3)) for s in (scene, tiny)]  # fmt: skip
    for view, tiny_view in zip(sets[0].fit, sets[1].fit):
        assert view.image.max() > 0.1 and torch.allclose(tiny_view.image, view.image, atol=1e-3)
    config = CompressConfig.for_preset("balanced", fit_views=3, eval_views=2, eval_resolution=32, max_levels=0,
                                       device="cpu", pictures=False)  # fmt: skip
    at_size, small = (compress(s, config=config).report for s in (scene, tiny))
    assert math.isfinite(small.fidelity.worst) and small.fidelity.worst == pytest.approx(at_size.fidelity.worst, abs=1)
    assert small.gaussians.stored == pytest.approx(at_size.gaussians.stored, rel=0.1)


def with_alpha(folder: Path) -> None:
    """The photographs of ``folder`` made RGBA: transparent where they show nothing (black), with white hidden
    there, which no compositing may show."""
    for png in folder.rglob("*.png"):
        rgb = np.asarray(Image.open(png).convert("RGB"))
        empty = (rgb == 0).all(axis=-1, keepdims=True)
        rgba = np.concatenate([np.where(empty, 255, rgb), np.where(empty, 0, 255)], axis=-1).astype(np.uint8)
        Image.fromarray(rgba, "RGBA").save(png)


def test_photographs_on_a_white_backdrop_are_matched_on_it(tmp_path):
    """Photographs without alpha carry their backdrop (NeRF-Synthetic's white): the job renders the upload on it, so
    it scores on white as on black, not a few dB for every pixel around the object, and its report names it."""
    scores = {}
    for name, backdrop in (("black", (0.0, 0.0, 0.0)), ("white", (1.0, 1.0, 1.0)), ("rgba", (0.0, 0.0, 0.0))):
        upload = photographed("global", tmp_path / name, n=800, photos=8, tests=2, resolution=48, backdrop=backdrop)
        if name == "rgba":
            with_alpha(tmp_path / name)
        config = CompressConfig.for_preset("balanced", fit_views=4, eval_views=2, eval_resolution=48,
                                           use_mirrors=False, device="cpu", pictures=False)  # fmt: skip
        scores[name] = compress(upload, images=tmp_path / name, config=config).report
    white, black = scores["white"], scores["black"]
    # Edges against white and against black differ a little (measured: 19.3 and 20.4 dB); drawn on black, the white
    # photographs scored about 3 dB.
    assert white.psnr_input == pytest.approx(black.psnr_input, abs=2.0) and white.psnr_input > 15.0
    assert white.fidelity.worst == pytest.approx(black.fidelity.worst, abs=2.0)
    assert white.fitting.worst >= white.psnr_floor > black.psnr_floor - 2.0
    assert white.cameras.background == pytest.approx((1.0, 1.0, 1.0), abs=2 / 255)
    # Photographs with alpha are composited on black, whatever colour their transparent pixels hide.
    assert black.cameras.background == scores["rgba"].cameras.background == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("alpha", [True, False], ids=["rgba", "rgb"])
def test_photographs_laid_on_another_background_are_those_read_on_it(tmp_path, monkeypatch, alpha):
    """A job that finds a backdrop lays what it read on it: every target is the one a read on that background gives,
    tensor for tensor (downscaled, so the alpha is resized too), and no image is read again."""
    from symgs_core.datasets import images

    backdrop = (0.0, 0.0, 0.0) if alpha else (1.0, 1.0, 1.0)
    upload = photographed("global", tmp_path, n=300, photos=6, tests=2, resolution=48, backdrop=backdrop)
    if alpha:
        with_alpha(tmp_path)
    read = functools.partial(dataset_views, tmp_path, upload, fit=2, eval=2, resolution=32)
    colour = torch.tensor([0.2, 0.5, 0.9])
    black = read(background=torch.zeros(3))
    direct = read(background=colour)
    monkeypatch.setattr(images, "read_premultiplied", lambda path: pytest.fail(f"{path.name} read again"))
    laid = black.on(colour)
    assert torch.equal(laid.background, colour) and laid.sets == direct.sets
    for ours, theirs, before in zip((laid.train, laid.fit, laid.eval), (direct.train, direct.fit, direct.eval),
                                    (black.train, black.fit, black.eval), strict=True):  # fmt: skip
        assert len(ours) == len(theirs) > 0
        for view, their in zip(ours, theirs, strict=True):
            assert torch.equal(view.image, their.image) and torch.equal(view.mask, their.mask)
            assert torch.equal(view.camera.R, their.camera.R) and torch.equal(view.camera.t, their.camera.t)
            assert view.camera.width == their.camera.width == 32
        # Where the photographs are transparent the new colour shows; opaque photographs keep their own backdrop.
        assert any(not torch.equal(a.image, b.image) for a, b in zip(ours, before, strict=True)) == alpha


@pytest.mark.parametrize("upload", ["another scene", "turned a quarter", "out of view"])
def test_photographs_that_do_not_show_the_upload_are_refused_before_any_work(tmp_path, upload):
    """Against the photographs of another scene, or with poses in another frame, every decision would chase noise
    (the floor falls to a few dB and any mirror passes it): the job is refused, by its code, before any work."""
    from symgs_core.datasets import DatasetError

    shown = photographed("global", tmp_path, n=800, photos=8, tests=2, resolution=48)
    centre = shown.means.mean(dim=0)
    quarter = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    uploads = {
        "another scene": lambda: synthetic_scene("asymmetric", n=800, seed=5, sh_degree=1).scene,
        "turned a quarter": lambda: shown.with_(means=(shown.means - centre) @ quarter.T + centre),
        "out of view": lambda: shown.with_(means=shown.means + 100.0),
    }
    config = CompressConfig.for_preset("balanced", iterations=5, fit_views=4, eval_views=2, eval_resolution=48,
                                       max_levels=1, device="cpu", pictures=False)  # fmt: skip
    steps = []
    with pytest.raises(DatasetError) as refused:
        compress(uploads[upload](), images=tmp_path, config=config, progress=lambda e: steps.append(e.stage))
    assert refused.value.code == "images_mismatch"
    assert "codec" not in steps and "levels" not in steps
    assert compress(shown, images=tmp_path, config=config).report.cameras.fitting.source == "photographs"


def test_photographs_of_one_flat_colour_are_refused_as_such():
    """Where the upload is drawn they hold a single colour (a blank set, or pictures read wrongly): no flat colour
    can be beaten there, and the message says what they show rather than an infinite PSNR."""
    from types import SimpleNamespace

    from symgs_core.cameras import View
    from symgs_core.datasets import DatasetError
    from symgs_core.views import check_photographs

    mask = torch.zeros(8, 8, dtype=torch.bool)
    mask[2:6, 2:6] = True
    views = [View(None, torch.full((8, 8, 3), 0.5), mask)] * 2
    with pytest.raises(DatasetError, match="one flat colour") as refused:
        check_photographs(SimpleNamespace(psnr_object=60.0), views)
    assert refused.value.code == "images_mismatch" and "inf" not in str(refused.value)


@pytest.mark.parametrize(
    ("attribute", "index", "value", "code", "named"),
    [
        ("means", (3, 0), math.nan, "non_finite", "x (1 values)"),
        ("scales", (4, 2), math.inf, "non_finite", "scale_2 (1 values)"),
        ("opacities", (5,), math.nan, "non_finite", "opacity (1 values)"),
        ("scales", (0, 1), 1e30, "out_of_range", "scale_1 (1 values beyond +-88)"),
        ("sh_dc", (2, 0), -1e5, "out_of_range", "f_dc_0 (1 values beyond +-4096)"),
    ],
)
def test_a_scene_in_memory_is_refused_as_its_file_would_be(attribute, index, value, code, named):
    """The Python API applies the PLY reader's rules before any work: the same code, naming the property, not an
    uncoded error from deep in the codec."""
    from symgs_core.ply import PlyError

    bad = synthetic_scene("global", n=200, seed=4).scene.clone()
    getattr(bad, attribute)[index] = value
    steps = []
    with pytest.raises(PlyError) as refused:
        compress(bad, config=FAST, progress=lambda e: steps.append(e.stage))
    assert refused.value.code == code
    assert str(refused.value).startswith("scene: ") and named in str(refused.value)
    assert set(steps) == {"load"}


def test_a_scene_in_memory_is_repaired_and_converted_as_its_file_would_be(tmp_path):
    """An infinite opacity is clamped as the reader clamps it (the caller's scene untouched), and float64 or float16
    attributes are taken as float32, as a PLY's double properties are: the archives are those of the scene's file."""
    from symgs_core.export import save_scene

    scene = synthetic_scene("global", n=200, seed=4).scene
    scene.opacities[7] = math.inf
    save_scene(scene, tmp_path / "scene.ply")
    from_file = compress(tmp_path / "scene.ply", config=FAST).archive
    assert compress(scene, config=FAST).archive == from_file
    assert scene.opacities[7].item() == math.inf
    assert compress(scene.map(lambda t: t.double()), config=FAST).archive == from_file
    half = scene.map(lambda t: t.half())
    save_scene(half.map(lambda t: t.float()), tmp_path / "half.ply")
    assert compress(half, config=FAST).archive == compress(tmp_path / "half.ply", config=FAST).archive


@pytest.mark.parametrize("count", [1, 3])
def test_gaussians_at_one_point_are_framed_whole_not_seen_from_inside(count: int):
    """The job's cameras keep their distance from a scene of no extent by the Gaussians' own size: each view holds
    the whole splat, the frame's border clear of it."""
    from symgs_core.render import render

    scene = synthetic_scene("global", n=200, seed=0, sh_degree=0).scene.select(torch.arange(count))
    scene = scene.with_(means=torch.zeros_like(scene.means) + 0.3, scales=torch.full_like(scene.scales, -3.0),
                        opacities=torch.full_like(scene.opacities, 3.0))  # fmt: skip
    views = self_supervised_views(scene, train=1, fit=2, eval=2, resolution=32, eval_resolution=32,
                                  background=torch.zeros(3))  # fmt: skip
    for view in [*views.fit, *views.eval]:
        alpha = render(scene, view.camera).alpha
        border = torch.cat([alpha[0], alpha[-1], alpha[:, 0], alpha[:, -1]])
        assert alpha.max() > 0.5 and border.max() < 0.05


@pytest.mark.parametrize("at", [0.0, 1e15])
def test_gaussians_all_at_one_point_are_compressed(at: float):
    """A point set of no size gets cameras a float apart from it, wherever it lies (far from the origin too)."""
    scene = synthetic_scene("global", n=200, seed=0, sh_degree=0).scene
    point = scene.with_(means=torch.zeros_like(scene.means) + at)
    config = CompressConfig.for_preset("balanced", fit_views=2, eval_views=2, eval_resolution=32, max_levels=0,
                                       device="cpu", pictures=False)  # fmt: skip
    report = compress(point, config=config).report
    assert report.fitting.worst >= report.psnr_floor and report.gaussians.decoded > 0
