"""Against photographs, the upload fine-tuned as a whole before the mirrors (``pipeline.refine``): kept only where
its archive is smaller, recorded in the report, resumed from its checkpoint, and never run where it cannot apply."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from symgs_core.bench.photos import photographed
from symgs_core.codec import decode_archive, expand_archive
from symgs_core.config import CompressConfig
from symgs_core.pipeline import compress
from symgs_core.pipeline import refine as refine_module
from symgs_core.views import dataset_views, evaluate

SMALL = {"iterations": 80, "fit_views": 3, "eval_views": 2, "eval_resolution": 48, "use_mirrors": False,
         "pictures": False}  # fmt: skip


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    """An upload sampled apart from the truth its photographs show: fine-tuning brings it nearer."""
    folder = tmp_path_factory.mktemp("capture")
    upload = photographed("asymmetric", folder, n=400, photos=8, tests=3, resolution=48, sh_degree=0, seed=1)
    return folder, upload


def test_an_upload_short_of_its_photographs_is_fine_tuned_and_its_smaller_archive_kept(capture) -> None:  # noqa: ANN001
    folder, upload = capture
    refined = compress(upload, images=folder, config=CompressConfig.for_preset(**SMALL), charts=False)
    record = refined.report.refinement
    assert record is not None and record.steps > 0, record
    assert record.psnr_after >= record.psnr_before + 0.05 and record.kept, record
    assert record.bytes_after is not None and record.bytes_after < record.bytes_before
    assert refined.report.output_bytes <= record.bytes_after  # the plain archive of the scene kept
    assert "kept" in record.reason and refined.report.seconds["refine"] > 0
    # The floor is the upload's: the fine-tune's gain is the codec's to spend, and the photographs that fitted
    # nothing score the archive no worse than the upload itself, less the budget.
    assert refined.report.psnr_floor == pytest.approx(record.psnr_before - refined.report.config.budget)
    assert refined.report.fidelity.worst >= refined.report.psnr_input - refined.report.config.budget - 0.5
    as_uploaded = compress(upload, images=folder, config=CompressConfig.for_preset(**{**SMALL, "iterations": 0}),
                           charts=False)  # fmt: skip
    assert as_uploaded.report.refinement is None
    assert as_uploaded.report.output_bytes == record.bytes_before
    assert refined.report.psnr_input == as_uploaded.report.psnr_input  # the upload's own, not the fine-tuned scene's


def test_a_fine_tune_that_gains_too_little_or_codes_larger_leaves_the_upload_as_it_came(capture,
                                                                                         monkeypatch) -> None:  # noqa: ANN001
    """The two ways a fine-tune is not kept, each giving the very archive of a job that fine-tunes nothing: a gain
    under ``MIN_GAIN_DB`` (a scene trained to convergence), or a scene whose archive is larger for all it gained."""
    folder, upload = capture
    as_uploaded = compress(upload, images=folder, config=CompressConfig.for_preset(**{**SMALL, "iterations": 0}),
                           charts=False)  # fmt: skip
    noise = torch.Generator().manual_seed(0)
    outcomes = {
        "converged": lambda fitted, job: (fitted.source, fitted.reference + 0.01, 80),
        "larger": lambda fitted, job: (fitted.source.with_(means=fitted.source.means + 1e-2 * torch.randn(
            fitted.source.means.shape, generator=noise)), fitted.reference + 1.0, 80),
    }  # fmt: skip
    for name, outcome in outcomes.items():
        monkeypatch.setattr(refine_module, "_fine_tune", outcome)
        result = compress(upload, images=folder, config=CompressConfig.for_preset(**SMALL), charts=False)
        record = result.report.refinement
        assert record is not None and not record.kept and "coded as it came" in record.reason, (name, record)
        assert (record.bytes_after is None) == (name == "converged"), (name, record)
        if name == "larger":
            assert record.bytes_after is not None and record.bytes_after >= record.bytes_before
        assert result.archive == as_uploaded.archive, name


def test_a_rerun_resumes_from_the_fine_tune_it_saved(capture, tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    folder, upload = capture
    config = CompressConfig.for_preset(**SMALL)
    first = compress(upload, images=folder, config=config, checkpoint_dir=tmp_path, charts=False)
    assert (tmp_path / "refined.pt").exists()

    def never(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("the fine-tune ran again")

    monkeypatch.setattr(refine_module, "optimize_level", never)
    again = compress(upload, images=folder, config=config, checkpoint_dir=tmp_path, charts=False)
    assert again.archive == first.archive and again.report.refinement == first.report.refinement


@pytest.mark.parametrize("preset", ["fast", "lossless"])
def test_presets_that_fit_nothing_or_keep_every_value_are_not_fine_tuned(capture, preset: str) -> None:  # noqa: ANN001
    folder, upload = capture
    result = compress(upload, images=folder, config=CompressConfig.for_preset(preset, **SMALL), charts=False)
    assert result.report.refinement is None
    if preset == "lossless":  # bit-exact attributes: the decode is the upload itself
        decoded = expand_archive(decode_archive(result.archive))  # in the archive's coding order
        assert sorted(map(tuple, decoded.means.tolist())) == sorted(map(tuple, upload.means.tolist()))


def test_without_photographs_nothing_is_fine_tuned(capture) -> None:  # noqa: ANN001
    _, upload = capture
    result = compress(upload, config=CompressConfig.for_preset(**{**SMALL, "resolution": 48}), charts=False)
    assert result.report.refinement is None and "refine" not in result.report.seconds


def test_the_fine_tune_renders_score_what_the_report_says(capture) -> None:  # noqa: ANN001
    folder, upload = capture
    result = compress(upload, images=folder, config=CompressConfig.for_preset(**SMALL), charts=False)
    views = dataset_views(folder, upload, fit=3, eval=2, resolution=48, background=torch.zeros(3))
    record = result.report.refinement
    assert record is not None
    assert evaluate(upload, views.fit, views.background, with_ssim=False).worst == pytest.approx(record.psnr_before)


def test_where_the_fine_tuned_scene_holds_no_mirror_the_first_is_sought_in_the_upload(capture,
                                                                                     monkeypatch) -> None:  # noqa: ANN001
    """Gaussian for Gaussian the fine-tuned scene is the upload's, so a mirror found in the upload indexes it; the
    working set is searched first."""
    import symgs_core.detect as detection

    folder, upload = capture
    seen, found = [], detection.detect

    def nothing_in_the_working_set(scene, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        seen.append(scene)
        return [] if len(seen) == 1 else found(scene, *args, **kwargs)

    monkeypatch.setattr(detection, "detect", nothing_in_the_working_set)
    config = CompressConfig.for_preset(**{**SMALL, "use_mirrors": True, "max_levels": 1})
    result = compress(upload, images=folder, config=config, charts=False)
    assert result.report.refinement is not None and result.report.refinement.kept
    assert len(seen) == 2 and not torch.equal(seen[0].means, upload.means)
    assert torch.equal(seen[1].means, upload.means)
