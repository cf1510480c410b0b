"""Symmetry detection: mirror planes of a Gaussian set and the membership of each side (DESIGN.md section 6)."""

from __future__ import annotations

from .config import DetectConfig
from .result import Mirror
from .search import detect

__all__ = ["DetectConfig", "Mirror", "detect"]
