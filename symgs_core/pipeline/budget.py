"""The codec that spends the PSNR budget: the fewest bytes whose predicted error stays within what the floor allows.

Each section has a ladder of quantisers: its step from 1/8 to 32 times the preset's, by sqrt 2 (higher SH also as a
palette of vectors, ``codec.palette``, at the same steps). A rung's bytes are estimated from its symbols (calibrated
by one real encode per section, ``Ladder``); its error is the sensitivity-weighted squared error of what it decodes
to (``sensitivity``), a prediction of the fitting renders' error. Entropy-coded quantisers trade one bit per coded
component for a quarter of the error, so a section's bits fall convexly as its error grows: at a price ``mu`` (bits
per unit of squared error) each section's best rung minimises bits + mu * error by itself, and one bisection on
``mu`` spends the allowed error, wherever it buys the most bytes. At the same price a Gaussian's highest SH bands go
when their error costs less than their bits are worth (model no more than the scene needs); Gaussians the renders
hardly miss are ranked here and removed as far as the renders allow (``encode``).

Rungs are evaluated lazily and kept, so moving ``mu`` costs a few estimates, and the calibration (``choose`` again
with the allowed error rescaled by what real renders measured, see ``encode``) costs none.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
import torch
from torch import Tensor

from ..codec.classes import OneStep, unwrapped
from ..codec.order import coding_order, grid_cells
from ..codec.palette import MAX_PALETTE, RowWeights, ShPaletteCodec, distinct_rows
from ..codec.quantize import (
    OpacityCodec,
    PositionCodec,
    RotationCodec,
    ScalarGridCodec,
    ShDcCodec,
    ShRestCodec,
    band_slices,
)
from ..codec.section import RateCodec, SectionCodec
from ..codec.steps import QuantSteps
from ..devices import HOST
from ..scene import GaussianScene
from .sensitivity import GroupedError, Sensitivity

RUNGS = range(-6, 11)  # a ladder's steps: 2^(k/2) times the preset's, 1/8 .. 32
# Below them, down to 2^-16 of the preset's step (about what float32 holds), only for a budget the finest of RUNGS
# cannot meet: it gets finer quantisers instead of an archive of float32 values. Not at every price: there the SH
# ladders of a 31k SH-degree-2 capture walked to steps near float32's at the default preset (618,606 B against
# 387,591 B, for 0.4 dB more on cameras that fitted nothing).
LOWEST = -32
_EXACT_PALETTE = 1 << 16  # distinct SH rows below which the palette holds every row exactly
_PALETTE = 1 << 14  # the k-means palette size otherwise
_MU_STEPS = 48  # bisection steps on the price (log scale)
RATE_SAMPLE = 1 << 16  # Gaussians whose encodes estimate a rung of a larger set (``Ladder``)


def extent_of(stored: GaussianScene) -> float:
    """Longest side of the stored set's bounding box (the position grid is relative to it)."""
    if len(stored) == 0:
        return 1.0
    means = stored.means.detach()
    return float((means.max(dim=0).values - means.min(dim=0).values).max())


@dataclass(frozen=True)
class Rung:
    codec: RateCodec
    bits: float
    error: float


class Ladder:
    """The rungs of one section, finest first, built by ``make(k)`` and evaluated on first use.

    A codec's bytes are not convex along its ladder everywhere: where it changes layout (values on a grid of their
    own at some steps, positions too fine for the Morton range) a rung can cost more than the next. Cheap sections
    are searched over every rung (``exhaustive``); the higher SH, whose encodes cost the most, walks downhill from
    where it last stood, looking two rungs ahead before it stops.

    A rung's bits are an estimate (``codec.estimate``: its symbols' statistics, no stream written) scaled by the
    ratio of one real encode to the estimate at the preset's own rung (k = 0): one encode per section, whatever the
    number of rungs visited. With ``sample`` (indices of the set, in coding order) a rung's bits and error are the
    sample's, scaled by the ratios of the whole set's estimates to the sample's at k = 0, and the encode is the
    sample's.
    """

    def __init__(self, section: str, values: np.ndarray, make: Callable[[int], RateCodec], sens: Sensitivity,
                 *, classes: np.ndarray | None = None, exhaustive: bool = True,
                 sample: np.ndarray | None = None) -> None:  # fmt: skip
        self.section, self.values, self.make, self.sens, self.classes = section, values, make, sens, classes
        self.exhaustive = exhaustive
        self._rungs: dict[int, Rung] = {}
        # The sample's weights of this section alone: a rung measures one section, and eleven ladders each holding
        # every section's weights of 65k Gaussians took 350 MB at SH degree 3.
        own = Sensitivity({section: sens.weights[section]})
        self._sample = None if sample is None else (values[sample], own.select(torch.from_numpy(sample)),
                                                    None if classes is None else classes[sample])  # fmt: skip
        self._scale: tuple[float, float] | None = None  # (bits, error): the whole set's real figures over estimates
        self._groups: tuple[np.ndarray, Sensitivity, GroupedError] | None = None  # (index, sens, what they give)

    def _measure(self, codec: RateCodec, values: np.ndarray, sens: Sensitivity,
                 classes: np.ndarray | None) -> tuple[float, float]:  # fmt: skip
        estimate = codec.estimate(values, classes=classes)
        if estimate.index is None:
            return estimate.bits, sens.error(self.section, values, estimate.decoded)
        # A palette's rows keep their groups from rung to rung (its fit does not depend on the steps).
        if self._groups is None or self._groups[0] is not estimate.index or self._groups[1] is not sens:
            self._groups = (estimate.index, sens, sens.grouped(self.section, values, estimate.index))
        return estimate.bits, self._groups[2].error(estimate.rows)

    @cached_property
    def _preset(self) -> tuple[RateCodec, tuple[float, float]]:
        """The preset's own rung (k = 0): its codec, and the estimate of what the rungs measure (the set, or its
        sample), which both that rung and the calibration use."""
        preset = self.make(0)
        return preset, self._measure(preset, *(self._sample or (self.values, self.sens, self.classes)))

    def rung(self, k: int) -> Rung:
        if k not in self._rungs:
            if self._scale is None:
                self._scale = self._calibration()
            if k == 0:
                codec, (bits, error) = self._preset
            else:
                codec = self.make(k)
                try:
                    bits, error = self._measure(codec, *(self._sample or (self.values, self.sens, self.classes)))
                except ValueError:  # a step too fine for the quantiser's grid (values beyond its cells)
                    bits, error = math.inf, math.inf
            self._rungs[k] = Rung(codec, bits * self._scale[0], error * self._scale[1])
        return self._rungs[k]

    def _calibration(self) -> tuple[float, float]:
        """(bits, error) of the whole set over the estimates, at the preset's own rung (k = 0): the real encode over
        the estimate of what the rungs measure (the set, or its sample), and with a sample, the whole set's estimate
        over the sample's (one real encode of the sample, not of a million Gaussians)."""
        preset, part = self._preset
        values, sens, classes = self._sample or (self.values, self.sens, self.classes)
        real = 8.0 * len(preset.encode(values, classes=classes).payload)
        bits = real / max(part[0], 1.0)
        if self._sample is None:
            return bits, 1.0
        whole = self._measure(preset, self.values, self.sens, self.classes)
        # Values already on the preset's grid (a scene decoded from a quantised format) err by nothing at k = 0:
        # then the errors scale as the sensitivity weights do.
        weight = float(self.sens.weights[self.section].sum()) / max(float(sens.weights[self.section].sum()), 1e-300)
        return bits * whole[0] / max(part[0], 1.0), whole[1] / part[1] if part[1] > 0 and whole[1] > 0 else weight

    def best(self, mu: float, start: int = 0, lowest: int = RUNGS.start) -> tuple[int, Rung]:
        """The rung minimising bits + mu * error, none finer than ``lowest``: over ``RUNGS`` when exhaustive, then
        downhill below them; else downhill from ``start``, looking two rungs ahead."""
        cost = lambda k: self.rung(k).bits + mu * self.rung(k).error  # noqa: E731
        k = min(RUNGS, key=cost) if self.exhaustive else min(max(start, lowest), RUNGS.stop - 1)
        moved = True
        while moved:
            moved = False
            for step in (-1, -2) if self.exhaustive else (1, 2, -1, -2):
                if lowest <= k + step < RUNGS.stop and cost(k + step) < cost(k):
                    k, moved = k + step, True
                    break
        return k, self.rung(k)


@dataclass
class Choice:
    """Each section's codec, which Gaussians stay, each one's SH degree, and what the model predicts of them."""

    codecs: dict[str, RateCodec]
    keep: Tensor  # [N] bool
    degrees: Tensor | None  # [N] SH degree kept (None: every band)
    errors: dict[str, float]  # predicted growth of the fitting MSE: "codec", "sh_reduction"
    bits: float  # predicted bits of the attribute sections
    mu: float
    rungs: dict[str, int] = field(default_factory=dict)

    @property
    def error(self) -> float:
        return sum(self.errors.values())


def _one_step(make: Callable[[int], RateCodec]) -> Callable[[int], RateCodec]:
    """The rungs of ``make`` with every Gaussian on the section's own step."""
    return lambda k: OneStep(make(k))


def palette_start(sh_rest: np.ndarray) -> int:
    """The palette size tried for ``sh_rest`` [N, K, 3]: every distinct non-zero row (exact) when they number fewer
    than ``_EXACT_PALETTE``, as in scenes decoded from SOG; else ``_PALETTE``."""
    rows = sh_rest.reshape(len(sh_rest), -1)
    distinct = distinct_rows(rows[rows.any(axis=1)])
    return min(distinct + 1 if distinct < _EXACT_PALETTE else _PALETTE, MAX_PALETTE)


class RateDistortion:
    """Ladders of every attribute section of ``stored`` (in its coding order), priced by ``sens``; each Gaussian
    quantised in its step class (``classes`` [N] int64, in the input's order: ``Sensitivity.step_classes`` unless
    given), and, where there are classes, each section on one step as well (``OneStep``), so that a section whose
    values already sit on a grid can be coded exactly on it while the others keep their classes."""

    def __init__(self, stored: GaussianScene, sens: Sensitivity, start: QuantSteps, *,
                 classes: Tensor | None = None) -> None:  # fmt: skip
        stored = stored.detach().to(HOST)  # the ladders' encodes run where the entropy coders do
        self.extent = extent_of(stored)
        self.classes = sens.step_classes() if classes is None else classes.to(HOST)
        cells = grid_cells(PositionCodec(start.position * max(self.extent, 1e-12)), stored.means.numpy(),
                           self.classes.numpy().astype(np.uint8))  # fmt: skip
        bits = torch.zeros(len(stored), 0, dtype=torch.bool, device=HOST)
        order = coding_order(stored, bits, cells, self.classes)
        self.order = order
        self.stored, self.sens = stored.select(order), sens.select(order)
        ordered = self.classes[order].numpy().astype(np.uint8)
        coded = ordered if ordered.any() else None
        self.start = start
        arrays = {k: v.contiguous().numpy() for k, v in self.stored.tensors().items()}
        n = len(self.stored)
        # Every (n / RATE_SAMPLE)-th Gaussian along the coding order: spread over the whole scene like the set.
        sample = np.linspace(0, n - 1, RATE_SAMPLE).round().astype(np.int64) if n > RATE_SAMPLE else None
        s, x = start, self.extent
        step = lambda base: (lambda k: base * 2.0 ** (k / 2))  # noqa: E731
        ladder = lambda name, make, coded=coded: Ladder(name, arrays[name], make, self.sens, classes=coded,  # noqa: E731
                                                        sample=sample)  # fmt: skip
        makers: dict[str, Callable[[int], RateCodec]] = {
            "means": lambda k: PositionCodec(step(s.position)(k) * max(x, 1e-12)),
            "quats": lambda k: RotationCodec(step(s.rotation)(k)),
            "scales": lambda k: ScalarGridCodec(step(s.scale)(k)),
            "opacities": lambda k: OpacityCodec(min(step(s.opacity)(k), 0.5)),
            "sh_dc": lambda k: ShDcCodec(step(s.dc)(k)),
        }
        # With classes, each section may also put every Gaussian on its own step (``codec.classes.OneStep``): on
        # values already on a grid, the finest steps, and the only ones a budget near lossless can take.
        self.ladders: dict[str, list[Ladder]] = {
            name: [ladder(name, make)] + ([] if coded is None else [ladder(name, _one_step(make), coded=None)])
            for name, make in makers.items()
        }
        self.ladders["sh_rest"] = self._sh_ladders(arrays["sh_rest"], sample, coded)
        self._at: dict[tuple[str, int], int] = {}
        self.lowest = RUNGS.start  # the finest rung any ladder takes: LOWEST once a budget needs more than RUNGS
        self._cost_err, self._nonzero_rows = self._truncation()

    def _sh_ladders(self, sh_rest: np.ndarray, sample: np.ndarray | None, classes: np.ndarray | None) -> list[Ladder]:
        """Per coefficient (in step classes), and, with higher bands, as a palette (weighted by each row's
        sensitivity, so rows the renders hardly see take coarser entry steps)."""
        bands = lambda k: tuple(b * 2.0 ** (k / 2) for b in self.start.sh)  # noqa: E731
        per = lambda k: ShRestCodec(bands(k))  # noqa: E731
        ladders = [Ladder("sh_rest", sh_rest, per, self.sens, classes=classes, exhaustive=False, sample=sample)]
        if classes is not None:
            ladders.append(Ladder("sh_rest", sh_rest, _one_step(per), self.sens, exhaustive=False, sample=sample))
        if self.stored.sh_degree:
            size = palette_start(sh_rest)
            weights = RowWeights.of(sh_rest, self.sens.per_gaussian("sh_rest").numpy())
            # A palette codes a vector per entry, not per Gaussian: its steps start finer by the square root of
            # entries per Gaussian, for the same error per coded component.
            finer = math.sqrt(min(1.0, size / max(len(sh_rest), 1)))
            palette = lambda k: ShPaletteCodec(size, tuple(b * finer for b in bands(k)), weights)  # noqa: E731
            # No sample: a sample's palette would be fitted to fewer rows, and its error would be the clustering's,
            # not the steps'.
            ladders.append(Ladder("sh_rest", sh_rest, palette, self.sens, exhaustive=False))
        return ladders

    @cached_property
    def _back(self) -> Tensor:
        """Each input index's position [N] in the coding order (``order``'s inverse)."""
        back = torch.empty_like(self.order)
        back[self.order] = torch.arange(len(self.order), device=self.order.device)
        return back

    def best(self, section: str, mu: float) -> tuple[int, int, Rung]:
        """The cheapest rung of ``section`` at price ``mu``: (ladder, rung index, rung)."""
        options = []
        for i, ladder in enumerate(self.ladders[section]):
            k, rung = ladder.best(mu, self._at.get((section, i), 0), self.lowest)
            self._at[(section, i)] = k
            options.append((rung.bits + mu * rung.error, i, k, rung))
        _, i, k, rung = min(options, key=lambda o: o[0])
        return i, k, rung

    def choose(self, allowed: float, *, keep: Tensor | None = None) -> Choice:
        """The choice at the price that spends ``allowed`` (predicted), or the finest rungs when nothing can.

        ``keep`` [N] bool, in the input's order: the Gaussians pruning kept (``prune_order``); every one when None.
        Bits scale with the share kept."""
        every = torch.ones(len(self.stored), dtype=torch.bool, device=HOST)
        kept = every if keep is None else keep.to(HOST)[self.order]
        # What every price shares: the kept share, and the truncation costs of the kept Gaussians alone (the
        # bisection asks for their SH degrees at each price, the choice returned for every Gaussian's).
        share = float(kept.double().mean()) if len(kept) else 1.0
        cost_err = self._cost_err[kept]
        lo, hi = 1e-3, 1e18  # bits per unit of MSE, bracketing every scene here
        choice = self._at_price(hi, kept, share, cost_err)
        if choice.error > allowed and self.lowest > LOWEST:
            self.lowest, hi = LOWEST, 1e30  # and a price that reaches float32's precision
            choice = self._at_price(hi, kept, share, cost_err)
        # Where even the finest rungs overspend, the choice is theirs: the caller falls back to storing values exactly.
        for _ in range(_MU_STEPS if choice.error <= allowed else 0):
            mu = math.sqrt(lo * hi)
            trial = self._at_price(mu, kept, share, cost_err)
            if trial.error <= allowed:
                hi, choice = mu, trial
            else:
                lo = mu
            if hi / lo < 1.02:
                break
        return replace(choice, degrees=self._sh_degrees(choice.mu, choice.codecs["sh_rest"], self._cost_err))

    def _at_price(self, mu: float, keep: Tensor, share: float, cost_err: Tensor) -> Choice:
        """The choice at price ``mu``, its SH degrees left out (None): ``cost_err`` [K, degree + 1] holds the
        truncation costs of the ``keep`` [N] Gaussians, whose share of the set is ``share``."""
        codecs, rungs, bits, error = {}, {}, 0.0, 0.0
        for section in self.ladders:
            i, k, rung = self.best(section, mu)
            codecs[section], rungs[section] = rung.codec, k
            bits, error = bits + rung.bits, error + rung.error
        errors = {"codec": error * share, "sh_reduction": 0.0}
        degrees = self._sh_degrees(mu, codecs["sh_rest"], cost_err)
        if degrees is not None:
            # The error of truncating to degree d is column d of the truncation costs.
            errors["sh_reduction"] = float(cost_err.gather(1, degrees[:, None])[:, 0].sum())
        return Choice(codecs, keep, None, errors, bits * share, mu, rungs)

    def prune_order(self) -> Tensor:
        """Indices [N] of the input, the Gaussians whose absence the renders would miss least first. Removal errors
        all darken towards the background and add up where they overlap, so how many may go is measured, not
        predicted (``encode.fit_codec``)."""
        removal = self.sens.removal(self.stored.opacities)
        return self.order[torch.argsort(removal, stable=True)]

    def _sh_degrees(self, mu: float, codec: SectionCodec, cost_err: Tensor) -> Tensor | None:
        """The SH degree of each Gaussian whose truncation costs are the rows of ``cost_err`` [M, degree + 1]: the
        lowest whose dropped bands cost less error than their bits are worth. A palette keeps whole rows (a partly
        dropped row would be a new palette entry): its rows go to the zero entry or stay."""
        degree = self.stored.sh_degree
        if not degree:
            return None
        total_bits = self.best("sh_rest", mu)[2].bits
        if isinstance(codec, ShPaletteCodec):
            row_bits = total_bits / max(self._nonzero_rows, 1)
            # Dropped where its error costs no more than its row's bits (at once truncated to degree 0: nothing left).
            return torch.where(mu * cost_err[:, 0] <= row_bits, 0, degree)
        widths = cost_err.new_tensor([0] + [s.stop - s.start for s in band_slices(degree)])
        per_coefficient = total_bits / max(self._nonzero_rows * int(widths.sum()), 1)
        kept_bits = torch.cumsum(widths, dim=0) * per_coefficient  # [degree + 1]
        cost = kept_bits[None, :] + mu * cost_err
        return cost.argmin(dim=1)

    def _truncation(self) -> tuple[Tensor, int]:
        """The error [N, degree + 1] of truncating each Gaussian to degree d (the weighted energy of bands
        d+1..degree), and how many Gaussians hold any higher SH."""
        w = self.sens.weights["sh_rest"]
        e = w * self.stored.sh_rest.to(torch.float64) ** 2
        slices = band_slices(self.stored.sh_degree)
        energy = torch.stack([e[:, s].sum(dim=(1, 2)) for s in slices], dim=1) if slices else e.new_zeros(len(e), 0)
        tail = torch.flip(torch.cumsum(torch.flip(energy, [1]), dim=1), [1])
        cost_err = torch.cat([tail, tail.new_zeros(len(energy), 1)], dim=1)
        nonzero = (self.stored.sh_rest != 0).reshape(len(energy), -1).any(dim=1)
        return cost_err, int(nonzero.sum())

    def apply(self, choice: Choice, *, pruning: bool = True, sh_reduction: bool = True) -> tuple[Tensor, GaussianScene]:
        """The stored set (in the input's order) as the choice leaves it: removed Gaussians gone, dropped SH bands
        zero; and the indices [M] of the input it keeps. Either reduction may be left out (for the accounting)."""
        stored = self.stored
        if choice.degrees is not None and sh_reduction:
            band_of = torch.tensor([math.isqrt(i + 1) for i in range(stored.sh_rest.shape[1])], device=stored.device)
            keep_band = band_of[None, :] <= choice.degrees[:, None]
            stored = stored.with_(sh_rest=stored.sh_rest * keep_band[:, :, None].to(stored.sh_rest.dtype))
        keep = choice.keep if pruning else torch.ones_like(choice.keep)
        kept = torch.sort(self.order[keep]).values
        return kept, stored.select(self._back[kept])

    def steps(self, choice: Choice) -> QuantSteps:
        """The steps the choice settled on, for the report."""
        c = {section: unwrapped(codec)[0] for section, codec in choice.codecs.items()}
        sh = getattr(c["sh_rest"], "steps", self.start.sh)
        palette = c["sh_rest"].size if isinstance(c["sh_rest"], ShPaletteCodec) else 0
        return replace(
            self.start, position=c["means"].step / max(self.extent, 1e-12), rotation=c["quats"].step,  # type: ignore[attr-defined]
            scale=c["scales"].step, opacity=c["opacities"].step, dc=c["sh_dc"].step,  # type: ignore[attr-defined]
            sh=tuple(sh), sh_palette=palette,
        )  # fmt: skip
