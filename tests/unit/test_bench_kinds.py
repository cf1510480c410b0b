"""Trained or decoded from a container, told by a scene's values: float32 values on no grid are a trainer's; a global
grid of a few hundred values (SOG's codebooks, `.spz`, `.splat`) or compressed PLY's lattice per chunk of 256 is a
container's."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from symgs_core.bench.kinds import CHUNK, chunk_lattice_share, container_grid
from symgs_core.scene import GaussianScene


def trained(n: int = 4096) -> GaussianScene:
    """A trainer's values: every field continuous (the synthetic scenes' generator may repeat values)."""
    g = torch.Generator().manual_seed(5)
    return GaussianScene(
        means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
        scales=torch.randn(n, 3, generator=g) - 4, opacities=torch.randn(n, generator=g),
        sh_dc=torch.randn(n, 3, generator=g), sh_rest=torch.randn(n, 3, 3, generator=g) * 0.1,
    )  # fmt: skip


def on_chunk_lattice(values: torch.Tensor, bits: int) -> torch.Tensor:
    """``values`` [N] as compressed PLY decodes them: 2^bits - 1 steps between each chunk's minimum and maximum."""
    chunks = values.reshape(-1, CHUNK).double()
    low, high = chunks.min(1, keepdim=True).values, chunks.max(1, keepdim=True).values
    steps = torch.round((chunks - low) / (high - low) * (2**bits - 1))
    return (low + steps / (2**bits - 1) * (high - low)).float().reshape(-1)


def test_a_trainers_values_are_on_no_grid() -> None:
    assert container_grid(trained()) is None


def test_a_codebook_of_a_few_hundred_values_is_a_containers_grid() -> None:
    scene = trained()
    codebook = torch.linspace(-9.0, -1.0, 256)
    scene.scales[:, 1] = codebook[torch.randint(0, 256, (len(scene),), generator=torch.Generator().manual_seed(1))]
    assert container_grid(scene) == f"scales[1]: 256 distinct values among {len(scene):,} Gaussians"


@pytest.mark.parametrize(("field", "bits"), [("sh_dc", 8), ("scales", 11), ("means", 10)])
def test_compressed_plys_lattice_per_chunk_is_found(field: str, bits: int) -> None:
    scene = trained()
    values = getattr(scene, field)
    values[:, 0] = on_chunk_lattice(values[:, 0] * 10 + 100, bits)  # far from zero beside their chunk's span too
    evidence = container_grid(scene)
    assert evidence is not None and evidence.startswith(f"{field}[0]: 100% of values on a {bits}-bit lattice")


def test_the_lattice_share_of_continuous_values_is_the_lattices_width() -> None:
    column = np.random.default_rng(0).normal(size=64 * CHUNK)
    assert chunk_lattice_share(column, 11) < 0.06  # 2 * ON_LATTICE of each step, and each chunk's two ends
    assert chunk_lattice_share(column[: CHUNK - 1], 8) == 0.0  # no whole chunk: no evidence


def test_a_small_scene_is_not_judged_by_its_count_of_values() -> None:
    scene = trained(300)
    g = torch.Generator().manual_seed(2)
    values = torch.randn(10, generator=g)  # ten values among 300 Gaussians: a count says nothing of so few
    scene.opacities[:] = values[torch.randint(0, 10, (300,), generator=g)]
    assert container_grid(scene) is None
