"""The Gaussian set: raw (pre-activation) attributes, as the graphdeco PLY stores them."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

# Number of non-DC SH coefficients per colour channel for each degree.
SH_REST_COUNT = {0: 0, 1: 3, 2: 8, 3: 15}


def sh_degree_for_rest(k: int) -> int:
    """SH degree whose non-DC coefficient count per channel is ``k``; ValueError otherwise."""
    for degree, count in SH_REST_COUNT.items():
        if count == k:
            return degree
    raise ValueError(f"{k} SH rest coefficients per channel match no SH degree 0..3 (expected 0, 3, 8 or 15)")


@dataclass
class GaussianScene:
    """N Gaussians with raw attributes.

    means      [N, 3]     world positions
    quats      [N, 4]     rotations, Hamilton quaternions (w, x, y, z), not necessarily normalised
    scales     [N, 3]     log standard deviations along the rotated axes
    opacities  [N]        opacity logits
    sh_dc      [N, 3]     DC SH coefficient per colour channel
    sh_rest    [N, K, 3]  higher SH coefficients, K = (degree + 1)^2 - 1, basis index major
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    sh_dc: Tensor
    sh_rest: Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expected = {
            "means": (n, 3),
            "quats": (n, 4),
            "scales": (n, 3),
            "opacities": (n,),
            "sh_dc": (n, 3),
        }
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"{name} has shape {got}, expected {shape}")
        rest = tuple(self.sh_rest.shape)
        if len(rest) != 3 or rest[0] != n or rest[2] != 3:
            raise ValueError(f"sh_rest has shape {rest}, expected ({n}, K, 3)")
        sh_degree_for_rest(rest[1])

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_for_rest(self.sh_rest.shape[1])

    @property
    def device(self) -> torch.device:
        return self.means.device

    def tensors(self) -> dict[str, Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def map(self, fn) -> GaussianScene:  # noqa: ANN001 - fn: Tensor -> Tensor
        """A new scene with ``fn`` applied to every attribute tensor."""
        return GaussianScene(**{k: fn(v) for k, v in self.tensors().items()})

    def to(self, device: torch.device | str) -> GaussianScene:
        return self.map(lambda t: t.to(device))

    def detach(self) -> GaussianScene:
        return self.map(lambda t: t.detach())

    def clone(self) -> GaussianScene:
        return self.map(lambda t: t.clone())

    def select(self, index: Tensor) -> GaussianScene:
        """Subset by a boolean mask [N] or an index tensor [M], in that order."""
        return self.map(lambda t: t[index])

    def with_(self, **changes: Tensor) -> GaussianScene:
        return replace(self, **changes)

    @staticmethod
    def cat(scenes: list[GaussianScene]) -> GaussianScene:
        if not scenes:
            raise ValueError("cannot concatenate an empty list of scenes")
        degrees = {s.sh_degree for s in scenes}
        if len(degrees) != 1:
            raise ValueError(f"cannot concatenate scenes of SH degrees {sorted(degrees)}")
        names = scenes[0].tensors().keys()
        return GaussianScene(**{k: torch.cat([s.tensors()[k] for s in scenes]) for k in names})

    @staticmethod
    def empty(sh_degree: int = 0, device: torch.device | str = "cpu") -> GaussianScene:
        k = SH_REST_COUNT[sh_degree]
        z = lambda *s: torch.zeros(*s, device=device)  # noqa: E731
        return GaussianScene(z(0, 3), z(0, 4), z(0, 3), z(0), z(0, 3), z(0, k, 3))

    # Activated values, as the renderer consumes them.
    def activated_opacities(self) -> Tensor:
        return torch.sigmoid(self.opacities)

    def activated_scales(self) -> Tensor:
        return torch.exp(self.scales)

    def normalized_quats(self) -> Tensor:
        return torch.nn.functional.normalize(self.quats, dim=-1)

    def sh_coeffs(self) -> Tensor:
        """All SH coefficients [N, K+1, 3], DC first."""
        return torch.cat([self.sh_dc[:, None, :], self.sh_rest], dim=1)
