"""Settings of a compression job: the preset table and one frozen object, decided here and nowhere else.

Every door (``symgs_core.compress``, ``symgs compress``, ``POST /v1/jobs``, ``symgs submit``, the dashboard) builds
its settings with ``CompressConfig.for_preset``: the preset's values, then the fields the caller set. The default
preset is ``DEFAULT_PRESET``. Standard library only: the API process reads the preset table without torch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, Literal, get_args

Preset = Literal["fast", "small", "balanced", "high", "lossless"]
DeviceChoice = Literal["auto", "cpu", "cuda"]
DEVICE_CHOICES: tuple[DeviceChoice, ...] = get_args(DeviceChoice)
PRESET_NAMES: tuple[str, ...] = get_args(Preset)
DEFAULT_PRESET: Preset = "balanced"


@dataclass(frozen=True)
class PresetSpec:
    """What a preset promises and how it starts: ``budget`` dB of PSNR (see ``CompressConfig``), the starting
    quantisation steps as a multiple of ``codec.QuantSteps()`` (``step_scale``; 0: float32, nothing quantised).

    ``fitted`` False: one encode at the starting steps, no mirrors, no renders deciding anything; the budget's floor
    is what the report compares the result with, not a promise. Preset ``fast`` starts at twice the preset steps,
    where ``balanced``'s fitted codecs land for most attributes on real captures (BENCHMARKS, "Scale").
    ``settings``: the preset's own defaults of other ``CompressConfig`` fields (a caller's values still win).
    """

    name: Preset
    budget: float
    step_scale: float
    summary: str
    fitted: bool = True
    settings: tuple[tuple[str, Any], ...] = ()


PRESETS: dict[str, PresetSpec] = {
    spec.name: spec
    for spec in (
        PresetSpec("fast", 0.3, 2.0, "seconds for a million Gaussians: one encode at fixed steps, no mirrors, no "
                   "fitting; fidelity is reported, not held to a floor", fitted=False,
                   settings=(("max_levels", 0), ("fit_views", 2), ("eval_views", 4))),
        PresetSpec("small", 1.0, 2.0, "smallest archives; up to 1 dB of PSNR below the input on a 30 dB scene"),
        PresetSpec("balanced", 0.3, 1.0, "the default; up to 0.3 dB of PSNR below the input on a 30 dB scene"),
        PresetSpec("high", 0.1, 0.5, "near-transparent; up to 0.1 dB of PSNR below the input on a 30 dB scene"),
        PresetSpec("lossless", 0.0, 0.0, "float32 attributes, bit-exact; only mirrors may cost fidelity"),
    )
}  # fmt: skip


def floor_for_budget(budget: float, nominal: float) -> float:
    """The PSNR (dB) against renders of the input that costs ``budget`` dB on a scene of ``nominal`` dB: the
    excess error E with 10 log10((e + E) / e) = budget, e the nominal error; +inf for a zero budget."""
    excess = 10.0 ** (budget / 10.0) - 1.0
    return math.inf if excess <= 0 else nominal - 10.0 * math.log10(excess)


def budget_for_floor(floor: float, nominal: float) -> float:
    """The budget whose floor (``floor_for_budget``) is ``floor``."""
    return 10.0 * math.log10(1.0 + 10.0 ** ((nominal - floor) / 10.0))


SEED_MAX = 2**31 - 1  # seeds as every door takes them: the CLI's --seed, the API's seed, CompressConfig.seed


@dataclass(frozen=True)
class Setting:
    """A job setting a caller may give beside its preset, the same at every door: a ``CompressConfig`` field, a
    ``JobParams`` field (left out or null: the preset's value) and an option of `symgs compress` and `symgs bench`
    (``flag``). Numbers lie in ``low`` .. ``high`` whichever door they came by: a job must fit a shared worker's
    means, and a local run of the same settings is the same job."""

    name: str
    kind: type[int] | type[float] | type[bool]
    help: str
    low: int | float | None = None
    high: int | float | None = None
    flag: str = ""  # the command line's option; "" for --name-with-dashes

    @property
    def option(self) -> str:
        return self.flag or "--" + self.name.replace("_", "-")

    @property
    def bounds(self) -> str:
        return f"{self.low}..{self.high}"

    def holds(self, value: float) -> bool:
        """Whether ``value`` lies within the bounds (a setting without any holds every value)."""
        return (self.low is None or self.low <= value) and (self.high is None or value <= self.high)


# What a caller may set beside ``preset`` and ``device`` (each a Literal above), in the order the doors list them.
JOB_SETTINGS: tuple[Setting, ...] = (
    Setting("psnr_budget", float, "dB of PSNR all lossy stages may cost together (default: the preset's)", 0, 60),
    Setting("max_levels", int, "cap on mirror levels", 0, 16),
    Setting("iterations", int, "optimisation steps per level", 0, 20_000),
    Setting("train_views", int, "cameras the fine-tune trains on (photographs: all that do not fit)", 1, 512),
    Setting("fit_views", int, "cameras every decision is taken on", 1, 256),
    Setting("eval_views", int, "cameras the report scores (fitted on nothing)", 1, 256),
    Setting("resolution", int, "longest side of the training views, pixels (photographs: the evaluation resolution)",
            16, 2048),  # fmt: skip
    Setting("eval_resolution", int, "longest side of the fitting and evaluation views, pixels", 16, 2048),
    Setting("use_mirrors", bool, "false (--no-mirrors): the plain codec alone, no mirror (the baseline)",
            flag="--no-mirrors"),  # fmt: skip
    Setting("seed", int, "seed of the camera rigs and the fine-tunes", 0, SEED_MAX),
)
SETTINGS_BY_NAME = {setting.name: setting for setting in JOB_SETTINGS}


@dataclass(frozen=True)
class CompressConfig:
    """What a compression job may spend and must keep. Build it with ``for_preset``.

    preset        the preset (``PRESETS``): its budget and starting steps; ``lossless`` stores float32 and spends
                  the budget on mirrors alone.
    psnr_budget   dB of PSNR all lossy stages together may cost, below the uncompressed scene (None: the preset's).
    nominal_psnr  fidelity (dB) a trained scene typically has against its own photographs (3DGS scores about 27.5
                  on Mip-NeRF 360, 29.5 on Deep Blending, 33 on NeRF-Synthetic). Without photographs the reference
                  is a render of the input, against which the input scores +inf; the budget then becomes the error
                  that, added to a scene of this nominal quality, would cost ``psnr_budget`` dB.
    max_levels    cap on mirror levels; the scene decides how many below the cap pay for themselves.
    iterations    most optimisation steps per level. A fine-tune runs in stretches of a quarter of them and stops after
                  the first stretch that gains less than 0.05 dB, so only a level still gaining runs them all: on a
                  trained capture with its photographs the first level gains 2.1 dB in 200 steps (too little to
                  pay), 3.0 dB in 800 and 3.7 dB in 1600, where a second level pays too (BENCHMARKS, "A real
                  capture with its photographs").
    train_views / fit_views / eval_views  camera counts of the three disjoint sets (``views``): the fine-tune trains
                  on the first, every decision is taken on the second, and only the third is reported. With
                  photographs, the dataset's test split is the evaluation set (at most ``eval_views`` of it).
                  Per-Gaussian decisions (pruning, SH bands) see only what the fitting cameras see: 16 of them cover
                  a capture where 8 left parts unseen that other cameras see (BENCHMARKS, "Pipeline").
    resolution    longest side, in pixels, of the training views when they are renders of the input; the fitting and
                  evaluation views are rendered at ``eval_resolution``. Photographs are all read at
                  ``eval_resolution`` and every training photograph that does not fit trains: a fine-tune trained on
                  them at a lower resolution than they are judged at falls short of what a level needs.
    pictures      draw the job's PNG pictures and charts into ``CompressResult.images``.
    """

    preset: Preset = DEFAULT_PRESET
    psnr_budget: float | None = None
    nominal_psnr: float = 30.0
    max_levels: int = 4
    iterations: int = 1600
    train_views: int = 128
    fit_views: int = 16
    eval_views: int = 8
    resolution: int = 192
    eval_resolution: int = 256
    device: DeviceChoice = "auto"
    use_mirrors: bool = True
    pictures: bool = True
    seed: int = 0
    detect: dict = field(default_factory=dict)  # overrides of DetectConfig fields

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"preset must be one of {', '.join(PRESET_NAMES)}, got {self.preset!r}")
        if self.psnr_budget is None:
            object.__setattr__(self, "psnr_budget", PRESETS[self.preset].budget)
        budget, budgets = self.budget, SETTINGS_BY_NAME["psnr_budget"]
        if not (math.isfinite(budget) and budgets.holds(budget)):
            raise ValueError(f"psnr_budget must be a number of dB in {budgets.bounds}, got {budget}")
        # PSNR of images in 0..1 is never below 0 dB, and photographs stored at 8 bits show at most about 59 dB.
        if not (isinstance(self.nominal_psnr, (int, float)) and 0 < self.nominal_psnr <= 60):
            raise ValueError(f"nominal_psnr must be a number of dB in (0, 60], got {self.nominal_psnr}")
        for setting in JOB_SETTINGS:
            value = getattr(self, setting.name)
            if setting.kind is int and not (isinstance(value, int) and setting.holds(value)):
                raise ValueError(f"{setting.name} must be in {setting.bounds}, got {value}")
        if not isinstance(self.detect, dict):
            raise ValueError(f"detect must be a dict of DetectConfig settings, got {self.detect!r}")
        if self.detect:  # imported only then: the package imports torch, which the API process (never given any) lacks
            from .detect.config import DetectConfig

            DetectConfig.with_overrides(self.detect)

    @classmethod
    def for_preset(cls, preset: str | None = None, **overrides: Any) -> CompressConfig:
        """The settings of ``preset`` (default ``DEFAULT_PRESET``) with every override that is not None.

        ValueError names an unknown setting or a value out of range.
        """
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise ValueError(f"unknown settings {', '.join(unknown)}")
        name = preset or DEFAULT_PRESET
        given = {k: v for k, v in overrides.items() if v is not None}
        own = dict(PRESETS[name].settings) if name in PRESETS else {}
        return cls(preset=name, **{**own, **given})  # type: ignore[arg-type]

    @property
    def budget(self) -> float:
        """``psnr_budget``, resolved (never None after construction)."""
        return float(self.psnr_budget if self.psnr_budget is not None else PRESETS[self.preset].budget)

    @property
    def quantized(self) -> bool:
        return PRESETS[self.preset].step_scale > 0

    def self_supervised_floor(self) -> float:
        """Minimum PSNR (dB) against renders of the input that keeps the loss within the budget."""
        return floor_for_budget(self.budget, self.nominal_psnr)
