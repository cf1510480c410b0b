"""The report of a finished job (``GET /v1/jobs/{id}/report``): ``symgs_core.report.Report`` field for field.

A test holds the two against each other. PSNRs are dB and null when infinite (a lossless result, or a scene
against itself); sizes are bytes, times seconds.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from .params import DevicePreference, Preset


class Fidelity(BaseModel):
    psnr: float | None = Field(description="dB over the full frame; null when infinite")
    psnr_object: float | None = Field(description="dB over the object's own pixels; null when infinite")
    ssim: float


class CameraSet(BaseModel):
    name: str = Field(description="training, fitting or evaluation")
    count: int
    source: str = Field(description="renders of the input, or photographs")
    resolution: int = Field(description="longest side, pixels")
    distances: tuple[float, float] | None = Field(description="nearest and farthest camera in scene radii")


class PhotoScale(BaseModel):
    width: int = Field(description="the photographs' own width, pixels (a distorted camera's undistorted frame)")
    height: int = Field(description="their own height, pixels")
    scale: float = Field(description="the share of that size every camera set decoded them at; 1: their own size")
    reason: str = Field(description="why that scale")


class Cameras(BaseModel):
    training: CameraSet
    fitting: CameraSet
    evaluation: CameraSet
    disjoint: bool = Field(description="no camera is in two sets: the reported figures were fitted on nothing")
    background: tuple[float, float, float] = Field(
        description="RGB in 0..1 every render of the job drew the scene on: black against renders of the input and "
        "photographs with alpha, else the flat backdrop the photographs show around the upload"
    )
    photographs: PhotoScale | None = Field(
        None, description="how the job read its photographs; null without them (targets rendered from the input)"
    )


class LevelReport(BaseModel):
    """One mirror level, kept or not; PSNRs on the fitting cameras."""

    level: int
    normal: tuple[float, float, float] = Field(description="unit normal n of the plane n.x = offset")
    offset: float
    votes: float
    left: int = Field(description="Gaussians kept and reflected")
    right: int = Field(description="Gaussians dropped because the reflection covers them")
    coverage: float
    psnr_before: float | None = Field(description="after dropping the right side, before the fine-tune")
    psnr_after: float | None
    stored_after: int
    seconds: float
    accepted: bool
    reason: str
    gate: float | None = Field(None, description="colour-agreement gate of the membership (null: geometry alone)")
    iterations: int = Field(0, description="fine-tune steps run (it stops once a stretch stops gaining)")
    archive_bytes: int | None = Field(None, description="the whole archive with this level, when it held the floor")
    found_in: Literal["scene", "part", "focus"] = Field(
        "scene",
        description="where its mirror was found: the whole scene, a spatially separate part of it, or the ball the "
        "photographs' cameras look at",
    )


class Refinement(BaseModel):
    """Against photographs, the upload fine-tuned as a whole before the mirrors; PSNRs on the fitting cameras, bytes of
    the plain codec's archive."""

    steps: int = Field(description="fine-tune steps run (it stops once a stretch stops gaining, or could not pay)")
    psnr_before: float | None = Field(description="the upload's")
    psnr_after: float | None
    bytes_before: int = Field(description="the upload's plain archive")
    bytes_after: int | None = Field(description="the fine-tuned scene's (null: not coded, it gained too little)")
    kept: bool = Field(description="whether the later stages start from the fine-tuned scene")
    reason: str
    seconds: float


class StageReport(BaseModel):
    """What one stage saved and cost; PSNR on the fitting cameras after it."""

    stage: str = Field(description="mirrors, pruning, sh_reduction, quantization, entropy_coding")
    bytes_before: int
    bytes_after: int
    saved_bytes: int
    psnr_after: float | None
    cost_db: float | None
    seconds: float
    removed: int | None = Field(None, description="pruning: Gaussians; sh_reduction: SH bands")
    predicted: bool = Field(False, description="psnr_after is the sensitivity model's prediction, not a render")


class Steps(BaseModel):
    position: float = Field(description="a fraction of the bounding box's longest side")
    rotation: float
    scale: float
    opacity: float
    dc: float
    sh: tuple[float, ...]
    sh_palette: int = Field(description="0: SH bands per coefficient; else at most this many palette entries")


class CodecReport(BaseModel):
    name: str = Field(description="lossless, or the preset whose fitted steps wrote the archive")
    steps: Steps | None = Field(description="null: float32, nothing quantised")
    floor: float | None = Field(description="the PSNR the steps were fitted to, on the fitting cameras")
    tries: int = Field(description="renders the step search took")


class SectionBytes(BaseModel):
    name: str = Field(description="header, means, quats, scales, opacities, sh_dc, bits, classes, or the higher "
                      "SH's parts: sh_degrees or sh_index, then sh_band_1 .. sh_band_3 (or sh_rest whole)")
    bytes: int


class GaussianCounts(BaseModel):
    input: int
    stored: int
    decoded: int


class ReportConfig(BaseModel):
    """The job's settings as the pipeline resolved them (``symgs_core.config.CompressConfig``)."""

    preset: Preset
    psnr_budget: float | None
    nominal_psnr: float
    max_levels: int
    iterations: int
    train_views: int
    fit_views: int
    eval_views: int
    resolution: int
    eval_resolution: int
    device: DevicePreference
    use_mirrors: bool
    pictures: bool
    seed: int
    detect: dict[str, float | int | bool]


class Report(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "scene": "chair.ply", "input_bytes": 1_240_000, "output_bytes": 81_000, "baseline_bytes": 122_000,
                    "plain_codec_bytes": 95_000, "ratio_to_ply": 15.3, "ratio_to_baseline": 1.51,
                    "gaussians": {"input": 5000, "stored": 2600, "decoded": 5000},
                    "fidelity": {"psnr": 43.2, "psnr_object": 41.9, "ssim": 0.994},
                    "psnr_floor": 41.6, "psnr_input": None,
                }  # fmt: skip
            ]
        },
    )

    scene: str = Field(description="the input's file name")
    input_bytes: int
    output_bytes: int
    baseline_bytes: int = Field(description="the codec alone on the input, at the archive's steps")
    plain_codec_bytes: int | None = Field(description="the pipeline without mirrors, when mirrors were tried")
    ratio_to_ply: float | None
    ratio_to_baseline: float
    gaussians: GaussianCounts
    levels: list[LevelReport]
    stages: list[StageReport]
    codec: CodecReport
    sections: list[SectionBytes] = Field(default_factory=list,
                                         description="where the archive's bytes are, in its order; they add up to "
                                         "output_bytes (empty in reports of earlier versions)")
    fidelity: Fidelity = Field(description="the decoded archive on the evaluation cameras, which fitted nothing")
    fitting: Fidelity = Field(description="the same on the fitting cameras, what the decisions saw")
    psnr_input: float | None = Field(description="the input on the evaluation cameras (null: renders of itself)")
    psnr_floor: float | None = Field(description="the promise, held by the worse of the two PSNRs when fitting")
    cameras: Cameras
    seconds: dict[str, float] = Field(description="per stage")
    device: str
    config: ReportConfig
    notes: list[str] = Field(default_factory=list,
                             description="what the user could do for a better result (send the photographs, ...)")
    refinement: Refinement | None = Field(None, description="against photographs: the upload's own fine-tune before "
                                          "the mirrors (null: none was run)")  # fmt: skip
    psnr_mirror_floor: float | None = Field(None, description="the fitting PSNR every mirror level held: psnr_floor "
                                            "or, against photographs, the plain archive's own where higher, so that "
                                            "a level is kept only where the archive is smaller at no lower fidelity "
                                            "(null: no level was tried)")  # fmt: skip
