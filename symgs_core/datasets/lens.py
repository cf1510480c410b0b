"""Lens distortion of real photographs, undone on load: COLMAP's SIMPLE_RADIAL, RADIAL, OPENCV and FULL_OPENCV
models and the ``k1 k2 k3 k4 p1 p2`` of instant-ngp and nerfstudio transforms files.

Each photograph is resampled to the pinhole camera COLMAP's ``image_undistorter`` (what 3DGS's converter runs) gives
it: the lens's focal lengths, and the largest frame about its principal point that holds no pixel from outside the
photograph (COLMAP's ``blank_pixels`` 0), so no black border is left and nothing is stretched; only the frame's
size and principal point change. The maps from the pinhole's pixels to the lens's are computed once per lens and
size (``undistortion_maps``) and every photograph of that lens goes through OpenCV's ``remap``.

Pixel coordinates put pixel centres at +0.5, as everywhere in this package; OpenCV puts them at integers, and the
maps handed to it are shifted by half a pixel for that.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from torch import Tensor

from .errors import DatasetError

# COLMAP's undistorter never shrinks a frame below a fifth of its size nor grows it past twice (min_scale, max_scale).
MIN_FRAME_SCALE, MAX_FRAME_SCALE = 0.2, 2.0
_NEWTON_STEPS = 100
_NEWTON_TOLERANCE = 1e-10  # normalised coordinates: a millionth of a pixel at any focal length a phone has


@dataclass(frozen=True)
class Lens:
    """A distorted camera for an image of ``width`` x ``height`` pixels: focal lengths and principal point (pixels),
    and the distortion of normalised coordinates (x, y) = ((u - cx) / fx, (v - cy) / fy), OpenCV's model:

        r2 = x^2 + y^2
        radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4) / (1 + d1 r2 + d2 r2^2 + d3 r2^3)
        x' = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
        y' = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

    ``radial`` is (k1, k2, k3, k4): k4 is nerfstudio's r^8 term; ``rational`` is (d1, d2, d3), the k4 k5 k6 of
    COLMAP's FULL_OPENCV (OpenCV's rational model); ``tangential`` is (p1, p2).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    radial: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    tangential: tuple[float, float] = (0.0, 0.0)
    rational: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def distorted(self) -> bool:
        return any(self.radial) or any(self.tangential) or any(self.rational)

    def scaled(self, sx: float, sy: float, width: int, height: int) -> Lens:
        """The same lens for its image resampled by ``sx`` and ``sy`` (pixel corners scale with them), now ``width``
        x ``height`` pixels (a reduced JPEG decode's last pixel may cover only part of a block)."""
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=width,
                       height=height)  # fmt: skip

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted normalised coordinates of undistorted ones (any shape, float64)."""
        k1, k2, k3, k4 = self.radial
        d1, d2, d3 = self.rational
        p1, p2 = self.tangential
        r2 = x * x + y * y
        radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))) / (1.0 + r2 * (d1 + r2 * (d2 + r2 * d3)))
        return (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)  # fmt: skip

    def undistort(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates of distorted ones, by Newton's method (the distortion has no closed
        inverse); DatasetError where it does not converge, a lens too strong to undo with a pinhole."""
        x, y = xd.copy(), yd.copy()
        h = 1e-7
        for _ in range(_NEWTON_STEPS):
            ex, ey = self.distort(x, y)
            ex, ey = ex - xd, ey - yd
            if max(np.abs(ex).max(initial=0.0), np.abs(ey).max(initial=0.0)) < _NEWTON_TOLERANCE:
                return x, y
            ax, ay = self.distort(x + h, y)
            bx, by = self.distort(x - h, y)
            cx, cy = self.distort(x, y + h)
            dx, dy = self.distort(x, y - h)
            j11, j21 = (ax - bx) / (2 * h), (ay - by) / (2 * h)
            j12, j22 = (cx - dx) / (2 * h), (cy - dy) / (2 * h)
            det = j11 * j22 - j12 * j21
            with np.errstate(divide="ignore", invalid="ignore"):
                x = x - (j22 * ex - j12 * ey) / det
                y = y - (j11 * ey - j21 * ex) / det
        raise DatasetError("distorted_camera", f"the lens distortion {self.coefficients()} cannot be undone over the "
                           f"whole {self.width}x{self.height} frame: it folds the image over itself")  # fmt: skip

    def coefficients(self) -> dict[str, float]:
        """The non-zero coefficients by their OpenCV names (for messages)."""
        names = {"k1": self.radial[0], "k2": self.radial[1], "k3": self.radial[2], "k4 (r^8)": self.radial[3],
                 "p1": self.tangential[0], "p2": self.tangential[1], "k4": self.rational[0], "k5": self.rational[1],
                 "k6": self.rational[2]}  # fmt: skip
        return {k: v for k, v in names.items() if v}


@lru_cache(maxsize=64)
def pinhole_for(lens: Lens) -> tuple[float, float, float, float, int, int]:
    """fx, fy, cx, cy, width and height of the pinhole camera ``lens`` is undistorted to, by COLMAP's rule.

    Every border pixel centre of the photograph is undistorted into the pinhole with the lens's own intrinsics; the
    frame is then scaled about the principal point, along each axis, to the innermost of them (so every pixel of
    the result samples the photograph), within ``MIN_FRAME_SCALE`` .. ``MAX_FRAME_SCALE``."""
    w, h = lens.width, lens.height
    along_x, along_y = np.arange(w) + 0.5, np.arange(h) + 0.5

    def border(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, y = lens.undistort((u - lens.cx) / lens.fx, (v - lens.cy) / lens.fy)
        return x * lens.fx + lens.cx, y * lens.fy + lens.cy

    left, right = border(np.full(h, 0.5), along_y)[0], border(np.full(h, w - 0.5), along_y)[0]
    top, bottom = border(along_x, np.full(w, 0.5))[1], border(along_x, np.full(w, h - 0.5))[1]
    cx, cy = lens.cx, lens.cy
    if not (left.max() < cx < right.min() and top.max() < cy < bottom.min()):
        raise DatasetError("distorted_camera", f"the lens distortion {lens.coefficients()} carries the photograph's "
                           "border past its principal point: no pinhole frame holds it")  # fmt: skip
    # The scale, per axis, at which the frame's outermost pixel centres (the principal point scaled with the frame)
    # meet the innermost undistorted border pixel centre on either side: COLMAP's rule, its half-pixel terms written
    # so that a lens without distortion keeps its frame.
    scale_x = min((cx + 0.5 - left.max()) / cx, (right.min() + 0.5 - cx) / (w - cx))
    scale_y = min((cy + 0.5 - top.max()) / cy, (bottom.min() + 0.5 - cy) / (h - cy))
    scale_x = float(np.clip(scale_x, MIN_FRAME_SCALE, MAX_FRAME_SCALE))
    scale_y = float(np.clip(scale_y, MIN_FRAME_SCALE, MAX_FRAME_SCALE))
    width, height = max(1, int(scale_x * w + 1e-9)), max(1, int(scale_y * h + 1e-9))
    return lens.fx, lens.fy, cx * width / w, cy * height / h, width, height


@dataclass(frozen=True)
class UndistortionMaps:
    """Where each pixel of a pinhole frame [H, W] samples its lens's photograph: OpenCV's ``map_x``, ``map_y``
    (float32, pixel centres at integers) and ``valid`` (bool: the sample lies on the photograph; False only where a
    lens needed more than ``MIN_FRAME_SCALE`` allows)."""

    map_x: np.ndarray
    map_y: np.ndarray
    valid: np.ndarray

    @property
    def all_valid(self) -> bool:
        return bool(self.valid.all())


def undistortion_maps(
    lens: Lens, fx: float, fy: float, cx: float, cy: float, width: int, height: int
) -> UndistortionMaps:
    """The maps from the pinhole ``fx fy cx cy`` of ``width`` x ``height`` pixels to ``lens``'s photograph."""
    x = ((np.arange(width) + 0.5 - cx) / fx)[None, :].repeat(height, axis=0)
    y = ((np.arange(height) + 0.5 - cy) / fy)[:, None].repeat(width, axis=1)
    xd, yd = lens.distort(x, y)
    u, v = xd * lens.fx + lens.cx, yd * lens.fy + lens.cy
    valid = (u >= 0.0) & (u <= lens.width) & (v >= 0.0) & (v <= lens.height)
    return UndistortionMaps((u - 0.5).astype(np.float32), (v - 0.5).astype(np.float32), valid)


def undistort_image(image: Tensor, maps: UndistortionMaps) -> Tensor:
    """``image`` [h, w, C] (float32, C <= 4: colour premultiplied by alpha, with it) resampled through ``maps``,
    bilinearly; samples a rounding past the photograph's edge read its edge pixels."""
    import cv2
    import torch

    out = cv2.remap(image.numpy(), maps.map_x, maps.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return torch.from_numpy(out.reshape(*maps.map_x.shape, image.shape[2]))
