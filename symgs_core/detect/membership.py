"""Which Gaussians a mirror explains, by geometric correspondence (scipy KD-tree).

Real captures reconstruct the two halves of a symmetric object independently, so their Gaussians rarely pair up one
to one. A Gaussian is *covered* when some Gaussian of the other side, reflected across the plane, lands within a
tolerance tied to the local spacing. Attribute agreement (colour, opacity, sizes, orientation) only scales the match
score, and a Gaussian is matched only where the mean score of its voxel on its side is high too, so that membership
forms regions, not specks. The covered Gaussians of one side are dropped (*right*), the Gaussians of the other side
that cover them are kept and reflected (*left*); everything else is *out*.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from .clusters import Attributes
from .pairs import Axes
from .refine import fit_reflection

# Attribute differences at which the agreement score falls to exp(-1/2): colour (RGB distance), opacity, log-scales.
_COLOUR_SCALE = 0.15
_OPACITY_SCALE = 0.3
_LOG_SCALE_SCALE = 0.7
_AXIS_SCALE = 0.1  # 1 - |cos| of the angle between the reflected distinct axis and the match's (0.1: ~25 deg)
_OWN_SCORE = 0.5  # a Gaussian is matched when its own score reaches this ...
_REGION_SCORE = 0.4  # ... and the mean score of its voxel on its side this: chance matches are specks, not regions
_PRIOR_COUNT = 1.5
_VOXEL_SPACINGS = 6.0  # voxel side, in typical spacings (about 9 Gaussians per voxel on a surface)
_SPACING_SAMPLE = 20_000  # Gaussians whose nearest neighbour sets the typical spacing
_CANDIDATES = 3  # nearest Gaussians across the plane each reflection is compared with
_ICP_SAMPLE = 50_000  # matched Gaussians used per plane-refinement step (plenty for a 3-parameter fit)


@dataclass(frozen=True)
class Sides:
    """Membership of the working set for one plane (indices into the working set, on its device)."""

    left: Tensor  # [L] kept and reflected
    right: Tensor  # [R] dropped: covered by reflected left Gaussians
    partner: Tensor  # [L] for each left Gaussian, the Gaussian of the other side its reflection lands nearest to
    score: Tensor  # [L] match score of each left Gaussian, 0..1


class Matcher:
    """Matches the sides of one working set for any plane; the KD-tree and the voxels are built once.

    points [N, 3] in the normalised frame; ``tolerance`` in local spacings (a reflected Gaussian that far off scores
    one half); ``attribute_weight`` 0..1 is how much attribute agreement may scale the score.
    """

    def __init__(
        self,
        points: Tensor,
        attrs: Attributes,
        axes: Axes,
        *,
        tolerance: float,
        attribute_weight: float,
    ) -> None:
        self.device = points.device
        self.axes = axes
        self.attrs = attrs
        self.tolerance = tolerance
        self.attribute_weight = attribute_weight
        self.p = points.detach().to(torch.float64).cpu().numpy()
        n = self.p.shape[0]
        self.tree = cKDTree(self.p)
        rng = np.random.default_rng(0)
        sample = rng.choice(n, size=min(n, _SPACING_SAMPLE), replace=False)
        self.sample = sample  # [S] Gaussians on which match rates are estimated
        self.icp_sample = rng.choice(n, size=min(n, _ICP_SAMPLE), replace=False)
        dist, _ = self.tree.query(self.p[sample], k=min(2, n), workers=-1)
        nearest = dist.reshape(len(sample), -1)[:, -1]
        positive = nearest[nearest > 0]
        # Coincident Gaussians have no spacing; fall back to a tiny fraction of the frame (radius 1).
        self.typical = float(np.median(positive)) if positive.size else 1e-3
        voxel = _VOXEL_SPACINGS * self.typical
        key = np.clip(np.floor(self.p / voxel), -(2**20), 2**20 - 1).astype(np.int64) + 2**20
        packed = (key[:, 0] << 42) | (key[:, 1] << 21) | key[:, 2]
        _, self.voxel, counts = np.unique(packed, return_inverse=True, return_counts=True)
        self.voxel = self.voxel.reshape(-1)
        # On a surface a voxel holds about (voxel / 2 spacing)^2 Gaussians: the local spacing follows from its count.
        local = 0.5 * voxel / np.sqrt(counts[self.voxel])
        # Never wider than typical: around sparse Gaussians (floaters, clutter) a wide tolerance matches by chance.
        self.spacing = np.clip(local, 0.5 * self.typical, 2.0 * self.typical)

    def sides(self, normal: Tensor, offset: float) -> Sides:
        """Membership for the plane normal.x = offset (normal [3] unit). The side with more matched Gaussians is
        kept (left); on a tie the side the normal points to."""
        n = normal.detach().to(torch.float64).cpu().numpy()
        d = self.p @ n - offset
        side = d > 0
        empty = torch.zeros(0, dtype=torch.long, device=self.device)
        if side.all() or not side.any():
            return Sides(empty, empty, empty, torch.zeros(0, device=self.device))
        tau = (self.tolerance * self.spacing)[:, None]
        err, hit = self._other_side(self.p - 2.0 * d[:, None] * n, side, d, 3.0 * float(tau.max()))  # [N, K]
        found = np.isfinite(err)
        hit = np.where(found, hit, np.arange(len(hit))[:, None])
        geo = np.where(found, np.exp(-math.log(2.0) * (np.where(found, err, 0.0) / tau) ** 2), 0.0)
        own = np.broadcast_to(np.arange(len(hit))[:, None], hit.shape)
        agree = self._agreement(own.ravel(), hit.ravel(), normal).reshape(hit.shape)
        w = self._attribute_trust(geo, agree)
        # Each Gaussian takes the best of its nearest candidates: with noise, the twin need not be the very nearest.
        scores = geo * (1.0 - w + w * agree)
        best = scores.argmax(axis=1)
        rows = np.arange(len(best))
        score, hit, found = scores[rows, best], hit[rows, best], found[rows, best]
        # Matched regions: a well-scored Gaussian in a voxel (on its side) that scores well on the whole.
        region = self.voxel * 2 + side
        # The mean is shrunk towards zero by _PRIOR_COUNT unmatched pseudo-Gaussians: a voxel holding a lone matched
        # Gaussian is a speck, not a region.
        mean = np.bincount(region, weights=score) / (np.bincount(region) + _PRIOR_COUNT)
        matched = (score >= _OWN_SCORE) & (mean[region] >= _REGION_SCORE)
        # A covered Gaussian needs a matched coverer, and a coverer a matched Gaussian to cover.
        cover = matched & matched[hit] & found
        count_a, count_b = int((cover & side).sum()), int((cover & ~side).sum())
        keep_side = side if count_a >= count_b else ~side
        keep = np.nonzero(cover & keep_side)[0]
        drop = np.nonzero(cover & ~keep_side)[0]

        def t(a: np.ndarray) -> Tensor:
            return torch.from_numpy(np.ascontiguousarray(a)).to(self.device)

        return Sides(t(keep), t(drop), t(hit[keep]), t(score[keep]).float())

    def match_rate(self, normal: Tensor, offset: float) -> float:
        """Share of (a fixed sample of) the Gaussians whose reflection lands within the tolerance of a Gaussian on
        the other side: the raw geometric evidence for a plane, before attributes and regions."""
        n = normal.detach().to(torch.float64).cpu().numpy()
        d_all = self.p @ n - offset
        i = self.sample
        d = d_all[i]
        err, hit = self.tree.query(self.p[i] - 2.0 * d[:, None] * n, k=1, workers=-1)
        crossed = (d_all[hit] > 0) != (d > 0)
        return float((crossed & (err < self.tolerance * self.spacing[i])).mean())

    def chance_rate(self, planes: int, seed: int) -> float:
        """Mean ``match_rate`` of random planes (random normals through random Gaussians): what any plane explains by
        chance here. Coarse or cluttered sets match much more by chance than finely sampled surfaces do."""
        gen = torch.Generator().manual_seed(seed)
        rates = []
        for _ in range(planes):
            n = torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=torch.float64), dim=0)
            at = int(torch.randint(self.p.shape[0], (1,), generator=gen))
            rates.append(self.match_rate(n, float(self.p[at] @ n.numpy())))
        return float(np.mean(rates)) if rates else 0.0

    def refine(self, normal: Tensor, offset: float, iters: int) -> tuple[Tensor, float]:
        """Iterated closest points: pair (a sample of) the Gaussians, reflected, with the nearest Gaussian of the
        other side within twice the tolerance, fit the plane to those pairs (``fit_reflection``), repeat.
        Returns the refined unit normal [3] (float64) and offset."""
        n = normal.detach().to(torch.float64).cpu()
        g = float(offset)
        idx = self.icp_sample
        a = self.p[idx]
        tau = self.tolerance * self.spacing[idx]
        for _ in range(iters):
            nn = n.numpy()
            d = a @ nn - g
            err, hit = self.tree.query(a - 2.0 * d[:, None] * nn, k=1, workers=-1)
            good = np.nonzero((err < 2.0 * tau) & ((self.p[hit] @ nn - g) * d < 0))[0]
            if good.size < 8:
                break
            h = torch.from_numpy(hit[good]).to(self.device)
            # Matches that look alike and lie close weigh most: clutter that happens to land near a surface does not.
            geo = np.exp(-math.log(2.0) * (err[good] / tau[good]) ** 2)
            agree = self._agreement(idx[good], hit[good], n)
            w = self._attribute_trust(geo, agree)
            new_n, new_g = fit_reflection(
                torch.from_numpy(a[good]),
                torch.from_numpy(self.p[hit[good]]),
                self.axes.u[h].cpu(),
                self.axes.flat[h].cpu(),
                torch.from_numpy(geo * (1 - w + w * agree)),
                n,
                g,
            )
            moved = math.acos(min(1.0, abs(float(new_n @ n)))) + abs(new_g - g)
            n, g = new_n, new_g
            if moved < 1e-7:
                break
        return n, g

    def _other_side(
        self, reflected: np.ndarray, side: np.ndarray, d: np.ndarray, cutoff: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The nearest Gaussians on the other side of the plane to each reflected Gaussian: distances [N, K] (inf
        beyond ``cutoff`` or on the own side) and indices [N, K], K = _CANDIDATES."""
        k = min(_CANDIDATES, self.p.shape[0])
        err, hit = self.tree.query(reflected, k=k, workers=-1)
        err, hit = err.reshape(-1, k), hit.reshape(-1, k)
        crossed = side[hit] != side[:, None]
        # A reflection lands |d| beyond the plane, so hits on its own side only happen near the plane or where the
        # other side has nothing close; where none crossed, look again among the other side's Gaussians near the plane.
        redo = np.nonzero(~crossed.any(axis=1) & (err[:, 0] < cutoff))[0]
        err = np.where(crossed, err, np.inf)
        for this_side in (True, False):
            mine = redo[side[redo] == this_side]
            if mine.size == 0:
                continue
            band = np.nonzero((side != this_side) & (np.abs(d) <= cutoff + np.abs(d[mine]).max()))[0]
            if band.size == 0:
                continue
            kb = min(k, band.size)
            e, h = cKDTree(self.p[band]).query(reflected[mine], k=kb, distance_upper_bound=cutoff, workers=-1)
            e, h = e.reshape(-1, kb), h.reshape(-1, kb)
            ok = np.isfinite(e)
            err[mine, :kb] = e
            hit[mine, :kb] = np.where(ok, band[np.minimum(h, band.size - 1)], hit[mine, :kb])
        err[err > cutoff] = np.inf
        return err, hit

    def _attribute_trust(self, geo: np.ndarray, agree: np.ndarray) -> float:
        """Weight of attribute agreement in the score: ``attribute_weight`` times the share of the geometrically
        close matches whose attributes agree. Exact twins agree, so attributes then reject clutter that happens to land
        near a surface; the independently reconstructed halves of a real capture mostly do not (colours, sizes and
        orientations differ), and geometry alone decides."""
        close = geo >= 0.9  # any shape: the test is per candidate
        if not close.any():
            return 0.0
        return self.attribute_weight * float((agree[close] > 0.5).mean())

    def _agreement(self, i: np.ndarray, j: np.ndarray, normal: Tensor) -> np.ndarray:
        """Soft agreement [M] in (0, 1] of Gaussians i [M] and j [M] as mirror images across a plane with ``normal``
        [3]: colour, opacity, sorted sizes, and the reflected distinct axis of i against that of j."""
        a, ax = self.attrs, self.axes
        i_t, j_t = torch.from_numpy(i).to(self.device), torch.from_numpy(j).to(self.device)
        dc = (a.rgb[i_t] - a.rgb[j_t]).norm(dim=1) / _COLOUR_SCALE
        do = (a.opacity[i_t] - a.opacity[j_t]) / _OPACITY_SCALE
        ds = (a.log_scales[i_t] - a.log_scales[j_t]).norm(dim=1) / _LOG_SCALE_SCALE
        n = normal.to(ax.u)
        u_i, u_j = ax.u[i_t], ax.u[j_t]
        cos = ((u_i - 2.0 * (u_i @ n)[:, None] * n) * u_j).sum(dim=1).abs()
        cos = torch.maximum(cos, ax.round[i_t].maximum(ax.round[j_t]))  # round Gaussians have no axis to disagree
        du = (1.0 - cos) / _AXIS_SCALE
        return torch.exp(-0.5 * (dc * dc + do * do + ds * ds + du * du)).double().cpu().numpy()
