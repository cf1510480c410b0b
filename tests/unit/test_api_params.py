"""Job parameters: what clients may send, and that every accepted value makes a valid pipeline config."""

from __future__ import annotations

import dataclasses
import json

import pytest

from api_schemas import JobParams
from service.api.errors import ApiError
from service.api.submission import parse_params
from symgs_core.config import CompressConfig
from worker.settings import Settings


def test_params_map_onto_the_pipeline_config() -> None:
    fields = {f.name for f in dataclasses.fields(CompressConfig)}
    assert set(JobParams.model_fields) - {"device"} <= fields
    # Nothing given: the default preset, every other setting the preset's, as symgs_core.compress() would use.
    assert CompressConfig.for_preset(**JobParams().pipeline_overrides()) == CompressConfig.for_preset()
    extremes = JobParams(preset="lossless", psnr_budget=60, max_levels=16, iterations=20_000, train_views=512,
                         fit_views=256, eval_views=256, resolution=2048, eval_resolution=2048, use_mirrors=False,
                         seed=2**31 - 1, device="cuda")  # fmt: skip
    assert set(extremes.pipeline_overrides()) == set(JobParams.model_fields) - {"device"}
    lows = JobParams(psnr_budget=0, resolution=16, eval_resolution=16, train_views=1, fit_views=1, eval_views=1)
    for device in ("cpu", "cuda"):
        CompressConfig.for_preset(**extremes.pipeline_overrides(), device=device)
        CompressConfig.for_preset(**lows.pipeline_overrides(), device=device)


@pytest.mark.parametrize(
    "text, where",
    [
        ("{", "params"), ("[]", "params"), ('{"iterations": -1}', "iterations"), ('{"resolution": 8}', "resolution"),
        ('{"preset": "huge"}', "preset"), ('{"device": "tpu"}', "device"), ('{"detect": {}}', "detect"),
        ('{"max_levels": 17}', "max_levels"), ('{"psnr_budget": "a lot"}', "psnr_budget"),
        ('{"psnr_budget": NaN}', "psnr_budget"), ('{"psnr_budget": true}', "psnr_budget"),
        ('{"psnr_budget": false}', "psnr_budget"),
    ],
)
def test_bad_params_are_named(text: str, where: str) -> None:
    with pytest.raises(ApiError) as caught:
        parse_params(text)
    assert (caught.value.status, caught.value.code) == (422, "bad_params")
    assert where in caught.value.message


@pytest.mark.parametrize(
    "text, message",
    [
        ("{", "params: Invalid JSON"), ("[]", "params: Input should be an object"),
        ('{"psnr_budget": NaN}', "params: psnr_budget: Input should be a finite number"),
        ('{"psnr_budget": "nan"}', "params: psnr_budget: Input should be a finite number"),
        ('{"psnr_budget": 1e999}', "params: psnr_budget: Input should be a finite number"),
    ],
)
def test_params_errors_read_plainly(text: str, message: str) -> None:
    with pytest.raises(ApiError) as caught:
        parse_params(text)
    assert caught.value.message.startswith(message), caught.value.message
    assert "params: params" not in caught.value.message


def test_missing_params_mean_defaults() -> None:
    assert parse_params(None) == parse_params("{}") == JobParams()
    # null is a field left out, for every field
    every = {name: None for name in JobParams.model_fields}
    assert parse_params(json.dumps(every)) == JobParams()
    assert parse_params('{"psnr_budget": "0.5"}').psnr_budget == 0.5


def test_settings_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SYMGS_API_KEYS", " a , b,,")
    monkeypatch.setenv("SYMGS_MAX_UPLOAD_BYTES", "1000")
    settings = Settings()
    assert settings.keys == ["a", "b"] and settings.max_upload_bytes == 1000
    assert settings.visibility_timeout > settings.hard_time_limit > settings.soft_time_limit
    with pytest.raises(ValueError, match="HARD_TIME_LIMIT"):
        Settings(soft_time_limit=100, hard_time_limit=50)
    assert Settings(storage="s3://symgs-jobs/prod").storage == "s3://symgs-jobs/prod"
    with pytest.raises(ValueError, match="directory path or s3://bucket/prefix"):
        Settings(storage="gs://symgs-jobs/prod")
    assert Settings(auth="none", api_keys="").keys == []
    with pytest.raises(ValueError, match="SYMGS_AUTH=none .* SYMGS_API_KEYS is set"):
        Settings(auth="none", api_keys="k")
