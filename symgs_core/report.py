"""The report of a compression job: one frozen, typed object that the pipeline produces and every layer reads.

``api_schemas.report`` mirrors it field for field (a test compares the two). ``as_json`` gives the strict JSON of
the HTTP API and the files: infinities (a lossless result, a scene against itself) become null. Sizes in bytes,
PSNR in dB, times in seconds. Standard library only.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from .config import CompressConfig


@dataclass(frozen=True)
class Fidelity:
    """PSNR (dB; +inf when identical) over the full frame and over the object's own pixels, and SSIM."""

    psnr: float
    psnr_object: float
    ssim: float

    @property
    def worst(self) -> float:
        """The PSNR a floor is held to: the lower of the two."""
        return min(self.psnr, self.psnr_object)


@dataclass(frozen=True)
class CameraSet:
    """One of the three disjoint camera sets (``views``)."""

    name: str  # training, fitting, evaluation
    count: int
    source: str  # "renders of the input" | "photographs"
    resolution: int  # longest side, pixels
    distances: tuple[float, float] | None  # nearest and farthest camera, in scene radii (None: photographs)


@dataclass(frozen=True)
class PhotoScale:
    """How a job read its photographs: their own size (a distorted camera's undistorted pinhole frame) and the share
    of it every camera set decoded them at, with why."""

    width: int  # pixels
    height: int
    scale: float  # 1: their own size; below it, the judges' resolution asked for less
    reason: str


@dataclass(frozen=True)
class Cameras:
    training: CameraSet
    fitting: CameraSet
    evaluation: CameraSet
    disjoint: bool  # no camera of one set is in another: the reported figures were fitted on nothing
    # RGB in [0, 1] every render of the job drew the scene on: black against renders of the input and against
    # photographs with alpha; the flat backdrop photographs without alpha show around the upload, where they show one
    background: tuple[float, float, float]
    photographs: PhotoScale | None = None  # None: no photographs, the targets are renders of the input


@dataclass(frozen=True)
class LevelReport:
    """One mirror level, kept or not; PSNRs on the fitting cameras."""

    level: int
    normal: tuple[float, float, float]  # unit normal n of the plane n.x = offset
    offset: float
    votes: float
    left: int  # Gaussians kept and reflected
    right: int  # Gaussians dropped because the reflection covers them
    coverage: float
    psnr_before: float  # after dropping the right side, before the fine-tune
    psnr_after: float
    stored_after: int
    seconds: float
    accepted: bool
    reason: str
    gate: float | None = None  # colour-agreement gate of the membership tried (None: geometry alone)
    iterations: int = 0  # fine-tune steps run (it stops once a stretch stops gaining)
    archive_bytes: int | None = None  # the whole archive with this level, when it held the floor
    found_in: str = "scene"  # "scene", "part" (a separate part of it) or "focus" (where the photographs look)


@dataclass(frozen=True)
class Refinement:
    """Against photographs, the upload fine-tuned as a whole before the mirrors (``pipeline.refine``); PSNRs on the
    fitting cameras, bytes of the plain codec's archive."""

    steps: int  # fine-tune steps run (it stops once a stretch stops gaining, or could no longer pay)
    psnr_before: float  # the upload's
    psnr_after: float
    bytes_before: int  # the upload's plain archive
    bytes_after: int | None  # the fine-tuned scene's (None: not coded, it gained too little)
    kept: bool  # whether the later stages start from the fine-tuned scene
    reason: str
    seconds: float


@dataclass(frozen=True)
class StageReport:
    """What one stage saved and cost; PSNR on the fitting cameras after it."""

    stage: str  # mirrors, pruning, sh_reduction, quantization, entropy_coding
    bytes_before: int
    bytes_after: int
    saved_bytes: int
    psnr_after: float
    cost_db: float | None
    seconds: float
    removed: int | None = None  # pruning: Gaussians; sh_reduction: SH bands
    predicted: bool = False  # psnr_after is the sensitivity model's prediction, not a render


@dataclass(frozen=True)
class Steps:
    """Quantisation steps of the archive; ``position`` is a fraction of the bounding box's longest side."""

    position: float
    rotation: float
    scale: float
    opacity: float
    dc: float
    sh: tuple[float, ...]
    sh_palette: int  # 0: higher SH bands per coefficient; else at most this many palette entries


@dataclass(frozen=True)
class CodecReport:
    name: str  # the archive codec: lossless, or the preset whose fitted steps wrote it
    steps: Steps | None  # None: float32, nothing quantised
    floor: float | None  # the PSNR the steps were fitted to, on the fitting cameras
    tries: int  # renders the step search took


@dataclass(frozen=True)
class SectionBytes:
    """Bytes of one part of the archive: ``header`` (its framing and header), a section (``means``, ``quats``,
    ``scales``, ``opacities``, ``sh_dc``, ``bits``, ``classes``), or the higher SH's parts: each Gaussian's degree
    (``sh_degrees``) or palette index (``sh_index``), then each band (``sh_band_1`` ..), or ``sh_rest`` whole."""

    name: str
    bytes: int


@dataclass(frozen=True)
class GaussianCounts:
    input: int
    stored: int
    decoded: int


@dataclass(frozen=True)
class Report:
    scene: str  # the input's file name ("scene" when given in memory)
    input_bytes: int  # of the input file; 0 when given in memory
    output_bytes: int
    baseline_bytes: int  # the codec alone on the input, at the archive's steps
    plain_codec_bytes: int | None  # the whole pipeline without mirrors, when mirrors were tried against it
    ratio_to_ply: float | None
    ratio_to_baseline: float
    gaussians: GaussianCounts
    levels: tuple[LevelReport, ...]
    stages: tuple[StageReport, ...]
    codec: CodecReport
    sections: tuple[SectionBytes, ...]  # where the archive's bytes are, in its order; they add up to output_bytes
    fidelity: Fidelity  # the decoded archive on the evaluation cameras: the figure a user reads
    fitting: Fidelity  # the same on the fitting cameras, what the decisions saw
    psnr_input: float  # the input on the evaluation cameras (+inf against renders of itself)
    psnr_floor: float  # the promise: fidelity.worst holds it on the fitting cameras
    cameras: Cameras
    seconds: dict[str, float]  # per stage
    device: str
    config: CompressConfig
    notes: tuple[str, ...] = ()  # what the user could do for a better result (send the photographs, ...)
    refinement: Refinement | None = None  # against photographs: the upload's own fine-tune (None: none was run)
    # The fitting PSNR every mirror level held: psnr_floor or, against photographs, the plain archive's own where
    # higher, so that a level is kept only where it is smaller at no lower fidelity (None: no level was tried)
    psnr_mirror_floor: float | None = None

    @property
    def accepted_levels(self) -> list[LevelReport]:
        return [level for level in self.levels if level.accepted]

    def as_json(self) -> dict[str, Any]:
        return _json_safe(dataclasses.asdict(self))


def _json_safe(value: Any) -> Any:
    """Infinities and NaN become null, tuples lists: strict JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value
