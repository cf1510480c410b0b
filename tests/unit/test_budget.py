"""The codec fitted to the budget: ladders against exhaustive search, the price bisection, SH bands and pruning that
pay, and fitted archives that keep their floor when rendered."""

from __future__ import annotations

import math

import pytest
import torch

from symgs_core.codec import decode_archive, expand_archive
from symgs_core.codec.classes import OneStep
from symgs_core.codec.steps import QuantSteps
from symgs_core.config import floor_for_budget
from symgs_core.metrics import mse_to_psnr, psnr_to_mse
from symgs_core.pipeline import budget, encode
from symgs_core.pipeline.budget import LOWEST, RUNGS, RateDistortion
from symgs_core.pipeline.encode import canonical, fit_codec, rate_model, write_archive
from symgs_core.pipeline.sensitivity import Sensitivity, sensitivity
from symgs_core.pipeline.state import LevelState
from symgs_core.report import Fidelity
from symgs_core.synthetic import synthetic_scene
from symgs_core.views import evaluate, self_supervised_views

FLOOR = floor_for_budget(0.3, 30.0)


@pytest.fixture(scope="module")
def setting():  # noqa: ANN201
    scene = synthetic_scene("global", n=900, seed=2, sh_degree=1).scene
    views = self_supervised_views(scene, train=1, fit=3, eval=2, resolution=16, eval_resolution=48,
                                  background=torch.zeros(3))  # fmt: skip
    state = canonical(LevelState.plain(scene))
    return state, views, sensitivity(state, views.fit, views.background)


def test_a_ladder_finds_the_cheapest_rung_at_every_price(setting) -> None:  # noqa: ANN001
    state, _, weights = setting
    rd = RateDistortion(state.stored, weights, QuantSteps())
    for section in ("means", "quats", "scales", "sh_dc", "sh_rest"):
        ladder = rd.ladders[section][0]
        rungs = {k: ladder.rung(k) for k in RUNGS}
        bits = [rungs[k].bits for k in RUNGS]
        errors = [rungs[k].error for k in RUNGS]
        assert errors[-1] > errors[0] and bits[-1] < bits[0], section  # coarser: fewer bits, more error
        for mu in (1e3, 1e6, 1e9, 1e12):
            best = min(RUNGS, key=lambda k: rungs[k].bits + mu * rungs[k].error)
            for start in (0,) if ladder.exhaustive else (RUNGS.start, 0, RUNGS.stop - 1):
                k, rung = ladder.best(mu, start)
                assert rung.bits + mu * rung.error == pytest.approx(rungs[best].bits + mu * rungs[best].error), (
                    section, mu, start)


def test_a_sampled_ladder_keeps_its_own_sections_weights_alone_and_prices_as_the_whole_set(
    setting, monkeypatch: pytest.MonkeyPatch  # noqa: ANN001
) -> None:
    """Past ``RATE_SAMPLE`` Gaussians a ladder measures its rungs on a sample of them: it keeps the sample's weights of
    its own section only (every section's, in each of eleven ladders, took 350 MB at 1M Gaussians with SH degree 3),
    and its preset rung is priced at the whole set's error."""
    state, _, weights = setting
    whole = RateDistortion(state.stored, weights, QuantSteps())
    monkeypatch.setattr(budget, "RATE_SAMPLE", 300)
    sampled = RateDistortion(state.stored, weights, QuantSteps())
    seen = set()
    for section, ladders in sampled.ladders.items():
        for ladder in ladders:
            if ladder._sample is not None:
                assert set(ladder._sample[1].weights) == {section}
                assert len(ladder._sample[0]) == 300
                seen.add(section)
    assert seen == set(sampled.ladders)
    for section in ("means", "quats", "scales", "opacities", "sh_dc", "sh_rest"):
        assert sampled.ladders[section][0].rung(0).error == pytest.approx(whole.ladders[section][0].rung(0).error,
                                                                         rel=1e-9)  # fmt: skip


def test_below_its_rungs_a_ladder_walks_only_where_it_is_let(setting) -> None:  # noqa: ANN001
    state, _, weights = setting
    rd = RateDistortion(state.stored, weights, QuantSteps())
    every = range(LOWEST, RUNGS.stop)
    for section in ("means", "scales", "sh_dc"):
        ladder = rd.ladders[section][0]
        rungs = {k: ladder.rung(k) for k in every}
        mu = 1e15  # a price past the finest of RUNGS
        best = min(every, key=lambda k: rungs[k].bits + mu * rungs[k].error)
        assert best < RUNGS.start, section
        assert ladder.best(mu)[0] == RUNGS.start, section
        k, rung = ladder.best(mu, lowest=LOWEST)
        assert rung.bits + mu * rung.error == pytest.approx(rungs[best].bits + mu * rungs[best].error), section


def test_the_price_spends_what_is_allowed_and_no_more(setting) -> None:  # noqa: ANN001
    state, _, weights = setting
    rd = RateDistortion(state.stored, weights, QuantSteps())
    choices = [rd.choose(allowed) for allowed in (1e-6, 1e-5, 1e-4)]
    for allowed, choice in zip((1e-6, 1e-5, 1e-4), choices):
        assert choice.error <= allowed
        assert choice.error >= 0.5 * allowed  # spent, within the ladders' granularity
    assert choices[0].bits > choices[1].bits > choices[2].bits


def test_sh_bands_the_renders_do_not_see_are_dropped(setting) -> None:  # noqa: ANN001
    state, _, weights = setting
    blind = dict(weights.weights)
    hidden = torch.arange(len(state.stored)) % 2 == 0
    blind["sh_rest"] = blind["sh_rest"].clone()
    blind["sh_rest"][hidden] = 0.0  # these Gaussians' view-dependent colour changes no pixel
    rd = RateDistortion(state.stored, Sensitivity(blind), QuantSteps())
    choice = rd.choose(1e-5)
    kept_in, stored = rd.apply(choice)
    assert len(kept_in) == len(state.stored)
    rest = stored.sh_rest.reshape(len(stored), -1)
    assert (rest[hidden] == 0).all() and (rest[~hidden] != 0).any()


def test_pruning_removes_what_no_camera_sees_first(setting) -> None:  # noqa: ANN001
    state, views, weights = setting
    stored = state.stored
    n = len(stored)
    invisible = stored.with_(opacities=torch.where(torch.arange(n) < 50, torch.tensor(-12.0), stored.opacities))
    scene = LevelState(invisible, state.normals, state.offsets, state.bits)
    rd = RateDistortion(invisible, sensitivity(scene, views.fit, views.background), QuantSteps())
    assert set(rd.prune_order()[:50].tolist()) == set(range(50))


@pytest.mark.parametrize("loss_db", [0.05, 0.3, 1.0, 3.0])
def test_pruning_renders_only_shares_that_can_pay_and_keeps_the_best(setting, monkeypatch, loss_db) -> None:  # noqa: ANN001
    """The share kept is the one an exhaustive search (every share rendered) keeps, and a share is rendered only
    when, as if its absence cost nothing, the codec would price it below the best so far."""
    state, views, weights = setting
    rd = RateDistortion(state.stored, weights, QuantSteps())
    allowed = psnr_to_mse(floor_for_budget(loss_db, 30.0))
    n, order = len(state.stored), rd.prune_order()
    best = (rd.choose(encode._AIM * allowed).bits, torch.ones(n, dtype=torch.bool))
    for share in encode.PRUNE_SHARES:  # the oracle
        keep = torch.ones(n, dtype=torch.bool)
        keep[order[: int(share * n)]] = False
        removed = encode._excess(encode._without(state, keep), views.fit, views.background, math.inf)
        bits = rd.choose(encode._AIM * allowed - removed, keep=keep).bits
        if removed < 0.5 * allowed and bits < best[0]:
            best = (bits, keep)
    excess, rendered = encode._excess, []
    monkeypatch.setattr(encode, "_excess", lambda s, *a: rendered.append(len(s.stored)) or excess(s, *a))
    keep, _ = encode.prune(state, rd, views.fit, views.background, allowed=allowed, psnr_before=math.inf)
    assert torch.equal(keep, best[1])
    assert 1 <= len(rendered) <= len(encode.PRUNE_SHARES) and rendered[0] == n - int(encode.PRUNE_SHARES[-1] * n)
    assert best[1].all() or int(best[1].sum()) in rendered  # the share kept was priced with its rendered error
    # The four budgets keep shares from the smallest (0.05 dB) to the largest (3 dB): at 3 dB, once the largest share
    # paid, no smaller one could be priced below it, so it is the only render. Pinned, so that a change of the
    # fixture that stops any budget from pruning the largest share fails here instead of skipping this check.
    largest = int((~best[1]).sum()) == int(encode.PRUNE_SHARES[-1] * n)
    assert largest == (loss_db == 3.0)
    if largest:
        assert len(rendered) == 1


def test_a_fitted_archive_keeps_its_floor_when_rendered(setting) -> None:  # noqa: ANN001
    state, views, _ = setting
    fitted = fit_codec(state, views.fit, views.background, floor=FLOOR, psnr_before=math.inf, start=QuantSteps(),
                       meta={}, name="balanced")  # fmt: skip
    decoded = expand_archive(decode_archive(fitted.archive))
    measured = evaluate(decoded, views.fit, views.background)
    assert measured.worst == pytest.approx(fitted.psnr) and measured.worst >= FLOOR
    assert fitted.fitting == measured  # the report's fitting scores, SSIM too, without rendering them again
    # The budget is spent, not hoarded: the error is most of what the floor allows.
    assert psnr_to_mse(measured.worst) >= 0.5 * psnr_to_mse(FLOOR)
    lossless = write_archive(state, {})
    assert len(fitted.archive) < 0.3 * len(lossless)
    assert [t["psnr"] >= FLOOR for t in fitted.tries][-1] or fitted.psnr >= FLOOR
    assert fitted.codec.steps is not None and fitted.codec.tries == len(fitted.tries) >= 1


def test_a_choice_the_model_gives_again_is_rendered_once(setting, monkeypatch) -> None:  # noqa: ANN001
    state, views, _ = setting
    # A model that gives one choice whatever the target: the search goes on re-aiming, the renders do not.
    choose, prune, asked = RateDistortion.choose, encode.prune, []
    fixed = 0.05 * psnr_to_mse(FLOOR)  # well within every target the search sets
    monkeypatch.setattr(encode, "prune", lambda *a, **k: (prune(*a, **k), asked.clear())[0])  # count the search's
    monkeypatch.setattr(RateDistortion, "choose", lambda self, allowed, keep=None: asked.append(allowed) or
                        choose(self, fixed, keep=keep))  # fmt: skip
    checked = []  # archives decoded to be rendered (pruning renders without one)
    monkeypatch.setattr(encode, "decode_archive", lambda data: checked.append(data) or decode_archive(data))
    fitted = fit_codec(state, views.fit, views.background, floor=FLOOR, psnr_before=math.inf, start=QuantSteps(),
                       meta={}, name="balanced")  # fmt: skip
    assert len(asked) >= 2  # the search asked again
    assert len(checked) == len(fitted.tries) == fitted.codec.tries == 1
    assert fitted.tries[0]["bytes"] == len(checked[0])


def test_no_room_under_the_floor_stores_float32(setting) -> None:  # noqa: ANN001
    state, views, _ = setting
    exact = fit_codec(state, views.fit, views.background, floor=math.inf, psnr_before=math.inf, start=QuantSteps(),
                      meta={}, name="balanced")  # fmt: skip
    assert exact.choice is None and exact.codec.name == "lossless"
    assert exact.archive == write_archive(state, {})
    float32 = fit_codec(state, views.fit, views.background, floor=FLOOR, psnr_before=math.inf, start=None,
                        meta={}, name="lossless")  # fmt: skip
    assert float32.codec.name == "lossless" and float32.psnr == math.inf


def test_the_rate_model_prices_what_a_change_to_the_state_costs_in_budget(setting) -> None:  # noqa: ANN001
    """A state that already errs spends part of the floor's budget, and its codec must be finer: the ratio the fitted
    rate model predicts for that is 1 where nothing changes, grows as the state's own PSNR falls, has no finite value
    at the floor, and agrees with a real fit of a degraded state."""
    state, views, _ = setting
    fitted = fit_codec(state, views.fit, views.background, floor=FLOOR, psnr_before=math.inf, start=QuantSteps(),
                       meta={}, name="balanced")  # fmt: skip
    assert rate_model(fitted, FLOOR)(math.inf, math.inf) == pytest.approx(1.0)
    ratios = [rate_model(fitted, FLOOR)(math.inf, FLOOR + d) for d in (6.0, 3.0, 1.0)]
    assert 1.0 < ratios[0] < ratios[1] < ratios[2]
    assert math.isinf(rate_model(fitted, FLOOR)(math.inf, FLOOR))
    rate = rate_model(fitted, FLOOR)  # below ``no_room`` nothing is left, whatever the codec: what lets renders stop
    assert FLOOR <= rate.no_room < FLOOR + 4.0
    assert all(math.isinf(rate(math.inf, rate.no_room - d)) for d in (1e-6, 0.5, 3.0))
    gen = torch.Generator().manual_seed(1)
    noisy = state.stored.with_(sh_dc=state.stored.sh_dc + 0.05 * torch.randn(state.stored.sh_dc.shape, generator=gen))
    degraded = LevelState(noisy, state.normals, state.offsets, state.bits)
    psnr = evaluate(degraded.expanded(), views.fit, views.background, with_ssim=False).worst
    assert FLOOR + 1.0 < psnr < FLOOR + 8.0
    refit = fit_codec(degraded, views.fit, views.background, floor=FLOOR, psnr_before=psnr, start=QuantSteps(),
                      meta={}, name="balanced")  # fmt: skip
    measured = len(refit.archive) / len(fitted.archive)
    assert measured > 1.0
    assert rate_model(fitted, FLOOR)(math.inf, psnr) == pytest.approx(measured, rel=0.3)


def test_a_budget_past_the_finest_rungs_gets_finer_steps_not_float32(setting) -> None:  # noqa: ANN001
    """Floors far above the balanced one: the size grows with the floor and stays quantised, well below float32;
    at the balanced floor no rung below RUNGS is taken."""
    state, views, _ = setting
    lossless, sizes = len(write_archive(state, {})), []
    for floor in (FLOOR, FLOOR + 30.0, FLOOR + 45.0):
        fitted = fit_codec(state, views.fit, views.background, floor=floor, psnr_before=math.inf, start=QuantSteps(),
                           meta={}, name="high")  # fmt: skip
        assert fitted.codec.name == "high" and fitted.psnr >= floor, (floor, fitted.tries)
        finest = min(fitted.choice.rungs.values())
        assert finest >= RUNGS.start if floor == FLOOR else finest < RUNGS.start, (floor, fitted.choice.rungs)
        sizes.append(len(fitted.archive))
    assert sizes[0] < sizes[1] < sizes[2] < 0.8 * lossless


def _on_grids(scene):  # noqa: ANN001, ANN202
    """``scene`` with its values on the uniform grids a quantised container decodes to (.spz-like steps)."""
    snap = lambda t, step: (torch.round(t / step) * step).to(t.dtype)  # noqa: E731
    alpha = torch.sigmoid(scene.opacities).clamp(1 / 255, 254 / 255)
    return scene.with_(means=snap(scene.means, 1 / 4096), scales=snap(scene.scales, 1 / 16),
                       sh_dc=snap(scene.sh_dc, 1 / 64), opacities=torch.logit(snap(alpha, 1 / 255)))  # fmt: skip


def test_step_classes_do_not_floor_a_budget_on_a_scene_already_on_grids() -> None:
    """On values already on a grid, finer steps cannot help: a step class's coarser multiples of the grid are an
    error no rung goes below. Each section may also put every Gaussian on its own step (``OneStep``), so a budget
    under that error is met quantised, not in float32, and the sections whose grid it needs leave the classes."""
    scene = _on_grids(synthetic_scene("global", n=900, seed=2, sh_degree=0).scene)
    views = self_supervised_views(scene, train=1, fit=3, eval=2, resolution=16, eval_resolution=48,
                                  background=torch.zeros(3))  # fmt: skip
    state = canonical(LevelState.plain(scene))
    weights = sensitivity(state, views.fit, views.background)
    rd = RateDistortion(state.stored, weights, QuantSteps())
    assert rd.classes.any()
    classed = {name: ladders[0] for name, ladders in rd.ladders.items()}
    floor_error = sum(ladder.rung(LOWEST).error for ladder in classed.values())  # the classes' error at best
    assert floor_error > 0
    assert rd.choose(1e-3 * floor_error).error <= 1e-3 * floor_error
    floor = mse_to_psnr(0.5 * floor_error / encode._AIM)  # a floor the classes' error alone would break
    fitted = fit_codec(state, views.fit, views.background, floor=floor, psnr_before=math.inf, start=QuantSteps(),
                       meta={}, name="high")  # fmt: skip
    assert fitted.codec.name == "high" and fitted.psnr >= floor, fitted.tries
    assert any(isinstance(codec, OneStep) for codec in fitted.choice.codecs.values())
    assert len(fitted.archive) < 0.8 * len(write_archive(state, {}))


def test_at_the_default_floor_a_scene_keeps_its_step_classes(setting) -> None:  # noqa: ANN001
    """Off any grid and at the balanced floor, coarser steps for the Gaussians the renders see least are what the
    classes are for: the fitted archive keeps them."""
    state, views, _ = setting
    fitted = fit_codec(state, views.fit, views.background, floor=FLOOR, psnr_before=math.inf, start=QuantSteps(),
                       meta={}, name="balanced")  # fmt: skip
    assert not all(isinstance(codec, OneStep) for codec in fitted.choice.codecs.values())
    assert decode_archive(fitted.archive).classes.any()


def test_the_checks_aim_only_between_a_target_that_held_the_floor_and_one_that_missed(setting, monkeypatch) -> None:  # noqa: ANN001
    """Renders that err more than the model, and more so the coarser the steps (error growing as the square of the
    predicted one): rescaled by the last check alone, the search would aim back at a target that already missed the
    floor. Kept between the largest target that held it and the smallest that missed it, every check is one that can
    improve, and the kept archive is the smallest that held."""
    state, views, _ = setting
    allowed = psnr_to_mse(FLOOR)
    choose, last, targets, checked = RateDistortion.choose, [], [], []

    def recorded(self, target, keep=None):  # noqa: ANN001, ANN202
        choice = choose(self, target, keep=keep)
        targets.append(target)
        last.append(choice.error)
        return choice

    def rendered(scene, views, background, with_ssim=True):  # noqa: ANN001, ANN202
        checked.append(targets[-1])
        error = last[-1]
        psnr = mse_to_psnr(error * (1.0 + max(0.0, 4.0 * (error / allowed - 0.5))))
        return Fidelity(psnr, psnr, 1.0)

    monkeypatch.setattr(encode, "prune", lambda state, rd, *a, **k: (torch.ones(len(rd.stored), dtype=torch.bool), 0.0))
    monkeypatch.setattr(RateDistortion, "choose", recorded)
    monkeypatch.setattr(encode, "evaluate", rendered)
    fitted = fit_codec(state, views.fit, views.background, floor=FLOOR, psnr_before=math.inf, start=QuantSteps(),
                       meta={}, name="balanced")  # fmt: skip
    held = [t for t, r in zip(checked, fitted.tries) if r["psnr"] >= FLOOR]
    assert len(fitted.tries) >= 3 and held  # a miss, a hold, then one between them
    for i, (target, tried) in enumerate(zip(checked, fitted.tries)):
        for later in checked[i + 1 :]:
            assert later > target if tried["psnr"] >= FLOOR else later < target
    assert len(fitted.archive) == min(r["bytes"] for r in fitted.tries if r["psnr"] >= FLOOR)
    # The bracket spent budget the first hold left unspent: a smaller archive, nearer the floor.
    first = next(r for r in fitted.tries if r["psnr"] >= FLOOR)
    assert len(fitted.archive) < first["bytes"] and FLOOR <= fitted.psnr < first["psnr"]
