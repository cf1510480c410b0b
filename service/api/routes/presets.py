"""``/v1/presets``: what each preset promises, and which one a job gets when it names none."""

from __future__ import annotations

from fastapi import APIRouter

from api_schemas import PresetInfo

from ..auth import OwnerDep
from ..errors import error_responses

router = APIRouter(prefix="/v1/presets", tags=["jobs"])


@router.get(
    "",
    response_model=list[PresetInfo],
    summary="List the presets",
    description="Every preset with its PSNR budget; `default` marks the preset of a job whose params name none.",
    responses=error_responses(401),
)
def list_presets(_: OwnerDep) -> list[PresetInfo]:
    return PresetInfo.listing()
