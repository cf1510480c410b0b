"""Symmetry detection: mirror planes of a Gaussian set and the membership of each side."""

from __future__ import annotations

import sys
import types
from typing import Any

from .config import DetectConfig
from .result import Mirror
from .search import detect

__all__ = ["DetectConfig", "Mirror", "detect"]


class _CallableModule(types.ModuleType):
    """``symgs_core.detect`` names both this package and its function. Once the package is imported, Python binds the
    name to the package, so ``from symgs_core import detect`` may yield either; calling the package runs the
    function, so both work."""

    def __call__(self, *args: Any, **kwargs: Any) -> list[Mirror]:
        return detect(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
