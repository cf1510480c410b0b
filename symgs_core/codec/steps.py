"""Quantisation steps of the stored set, the presets' starting points, and the archive codecs built from them.

The steps are balanced for rate against rendered error: with entropy-coded uniform quantisers, each halving of a
step costs one bit per coded component and divides that attribute's squared error by four, so the cheapest way to a
given image error gives every coded component the same share of it. Measured on the real scenes (excess MSE of the
render when one attribute alone is quantised, 6 held-out views at 192 px; fox 50k SH0 and playbot 125k SH2 agree
within 1.5x): rotations tolerate 6x the step of the DC colour's share, log-scales 2x, positions and opacity about
the same, SH bands half. ``scaled(f)`` moves every step together; the pipeline searches ``f`` for the PSNR budget.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import cast

from ..report import Steps
from .classes import CLASSES
from .masks import MASKS
from .palette import RowWeights, ShPaletteCodec
from .quantize import OpacityCodec, PositionCodec, RotationCodec, ScalarGridCodec, ShDcCodec, ShRestCodec
from .registry import ArchiveCodec, register_archive_codec, register_section_codec
from .section import SectionCodec

C0 = 0.28209479177387814


@dataclass(frozen=True)
class QuantSteps:
    """Grid steps of each attribute at scale 1; ``position`` is a fraction of the bounding box's longest side.

    ``sh_palette``: 0 stores the higher SH bands per coefficient (``ShRestCodec``), else as a palette of at most this
    many vectors and an index per Gaussian (``ShPaletteCodec``), the palette on the ``sh`` steps; ``sh_weights``, the
    render weight of the stored set's SH rows, lets the palette give entries the image depends on little coarser
    steps (not a step of its own: carried along, never compared or reported).
    """

    position: float = 2.0**-16
    rotation: float = 6.0 / 512.0
    scale: float = 1.0 / 16.0
    opacity: float = 1.2 / 128.0
    dc: float = 1.0 / (128.0 * C0)
    sh: tuple[float, float, float] = (1.0 / 32.0, 1.0 / 32.0, 1.0 / 32.0)
    sh_palette: int = 0
    sh_weights: RowWeights | None = field(default=None, compare=False, repr=False)

    def scaled(self, factor: float) -> QuantSteps:
        """Every step times ``factor`` (> 0); opacity stays within the unit interval; the palette size stays."""
        if not factor > 0:
            raise ValueError(f"step factor must be positive, got {factor}")
        return replace(
            self,
            position=self.position * factor,
            rotation=self.rotation * factor,
            scale=self.scale * factor,
            opacity=min(self.opacity * factor, 0.5),
            dc=self.dc * factor,
            sh=cast(tuple[float, float, float], tuple(s * factor for s in self.sh)),
        )

    def codecs(self, extent: float) -> dict[str, SectionCodec]:
        """Section codecs for a stored set whose bounding box's longest side is ``extent``."""
        return {
            "means": PositionCodec(self.position * max(extent, 1e-12)),
            "quats": RotationCodec(self.rotation),
            "scales": ScalarGridCodec(self.scale),
            "opacities": OpacityCodec(self.opacity),
            "sh_dc": ShDcCodec(self.dc),
            "sh_rest": ShPaletteCodec(self.sh_palette, self.sh, self.sh_weights)
            if self.sh_palette > 0
            else ShRestCodec(self.sh),
            "bits": MASKS,
            "classes": CLASSES,
        }

    def archive_codec(self, extent: float, name: str = "quantized") -> ArchiveCodec:
        """The archive codec writing a stored set whose bounding box's longest side is ``extent`` with these steps."""
        return ArchiveCodec(name, self.codecs(extent))

    def report(self) -> Steps:
        return Steps(self.position, self.rotation, self.scale, self.opacity, self.dc, tuple(self.sh), self.sh_palette)


# Readers of this build know every quantising codec, whatever step a writer chose.
register_archive_codec("quantized", QuantSteps().codecs(1.0))
register_section_codec(ShPaletteCodec(1, QuantSteps().sh))
