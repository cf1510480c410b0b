"""A small, complete job report for tests that read one without running the pipeline."""

from __future__ import annotations

import math
from dataclasses import replace

from symgs_core.config import CompressConfig
from symgs_core.report import (
    Cameras,
    CameraSet,
    CodecReport,
    Fidelity,
    GaussianCounts,
    LevelReport,
    Report,
    SectionBytes,
    StageReport,
    Steps,
)

LEVEL = LevelReport(level=0, normal=(1.0, 0.0, 0.0), offset=0.5, votes=3.0, left=10, right=9, coverage=0.9,
                    psnr_before=41.0, psnr_after=40.0, stored_after=91, seconds=1.0, accepted=True,
                    reason="within budget")  # fmt: skip


def sample_report() -> Report:
    cameras = [CameraSet(name, 4, "renders of the input", 64, (1.6, 2.8)) for name in ("training", "fitting",
                                                                                      "evaluation")]  # fmt: skip
    return Report(
        scene="s.ply", input_bytes=100, output_bytes=10, baseline_bytes=15, plain_codec_bytes=12, ratio_to_ply=10.0,
        ratio_to_baseline=1.5, gaussians=GaussianCounts(100, 91, 100),
        levels=(LEVEL, replace(LEVEL, level=1, accepted=False, reason="below the floor")),
        stages=(StageReport("quantization", 50, 20, 30, 45.0, 1.0, 0.5, removed=None),),
        codec=CodecReport("balanced", Steps(1e-4, 0.01, 0.06, 0.01, 0.03, (0.03,), 0), 41.6, 5),
        sections=(SectionBytes("header", 4), SectionBytes("means", 3), SectionBytes("sh_band_1", 3)),
        fidelity=Fidelity(math.inf, 44.0, 1.0), fitting=Fidelity(50.0, 45.0, 0.999), psnr_input=math.inf,
        psnr_floor=41.6, cameras=Cameras(*cameras, disjoint=True, background=(0.0, 0.0, 0.0)),
        seconds={"load": 0.25, "levels": 2.0}, device="cpu", config=CompressConfig.for_preset(),
    )  # fmt: skip


def decoded_by_sections(stored, steps, extent: float):  # noqa: ANN001, ANN201 - GaussianScene, QuantSteps
    """``stored`` as each section codec of ``steps`` encodes and decodes it on its own (no archive around)."""
    import torch

    from symgs_core.scene import GaussianScene

    codecs = steps.codecs(extent)
    out = {}
    for name, value in stored.tensors().items():
        array = value.detach().cpu().contiguous().numpy()
        coded = codecs[name].encode(array)
        out[name] = torch.from_numpy(codecs[name].decode(coded.payload, array.shape, coded.params, coded.raw_length))
    return GaussianScene(**out)
