"""What a mirror level trains and what the archive stores: the working set, the planes and the level bits."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..mirror import Plane, expand
from ..scene import GaussianScene


@dataclass
class LevelState:
    """What a level trains and what the archive stores: the working set, the planes (level 0 first), the bits."""

    stored: GaussianScene
    normals: Tensor  # [L+1, 3]
    offsets: Tensor  # [L+1]
    bits: Tensor  # [|S|, L+1] bool

    @staticmethod
    def plain(scene: GaussianScene) -> LevelState:
        """No mirror: the scene stored as it is."""
        dev, dtype = scene.device, scene.means.dtype
        return LevelState(
            scene,
            torch.zeros(0, 3, device=dev, dtype=dtype),
            torch.zeros(0, device=dev, dtype=dtype),
            torch.zeros(len(scene), 0, dtype=torch.bool, device=dev),
        )

    @property
    def planes(self) -> list[Plane]:
        """The levels' planes (level 0 first) as the archive stores them: unit normals."""
        return [Plane.from_tensor(n, g) for n, g in zip(self.normals, self.offsets, strict=True)]

    def expanded(self) -> GaussianScene:
        return expand(self.stored, self.normals, self.offsets, self.bits)[0]

    def detach(self) -> LevelState:
        return LevelState(
            self.stored.detach().clone(),
            self.normals.detach().clone(),
            self.offsets.detach().clone(),
            self.bits.clone(),
        )
