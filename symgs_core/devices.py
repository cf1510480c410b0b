"""Where tensors live. A job picks its device once (``resolve_device``); from there every tensor takes its device and
dtype from its inputs, so the CPU and a GPU run the same code.

Some work runs on the host whatever the job's device, and moves there in one visible place each:
  - cameras and other geometry built from host numbers (``cameras``), moved to the scene's device where they render;
  - symmetry detection (``detect.search.detect``): compiled CPU passes and scipy's KD-trees;
  - the codec (``pipeline.encode.write_archive``, ``pipeline.budget.RateDistortion``): the entropy coders, the
    palettes' k-means and the rate ladders; the archive decodes there and moves back to the job's device;
  - the CPU renderer's compiled kernels (``render._cpu``), which only a CPU job calls.
A constant built once (an SH sample basis, the cube's rotations, an SSIM window) is cached per device.
"""

from __future__ import annotations

import torch

HOST = torch.device("cpu")


def resolve_device(choice: str) -> torch.device:
    """The device a job runs on: CUDA for ``cuda`` (an error without one) and for ``auto`` where one is available."""
    if choice == "cuda" or (choice == "auto" and torch.cuda.is_available()):
        if not torch.cuda.is_available():
            raise ValueError("device 'cuda' requested but no CUDA device is available")
        return torch.device("cuda")
    return HOST
