"""Which Gaussians a mirror explains, by geometric correspondence (scipy KD-tree).

Real captures reconstruct the two halves of a symmetric object independently, so their Gaussians rarely pair up one
to one. A Gaussian is *covered* when some Gaussian of the other side, reflected across the plane, lands within a
tolerance tied to the local spacing. Attribute agreement (colour, opacity, sizes, orientation) only scales the match
score, and a Gaussian is matched only where the mean score of its voxel on its side is high too, so that membership
forms regions, not specks. The covered Gaussians of one side are dropped (*right*), the Gaussians of the other side
that cover them are kept and reflected (*left*); everything else is *out*.

The matching runs on the CPU (numpy, scipy's KD-tree, compiled numba kernels) whatever the device of the scene;
results go back to that device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from numba import prange
from scipy.spatial import cKDTree
from torch import Tensor

from ..compiled import compiled, compiled_parallel
from ..devices import HOST
from ..zorder import AXIS_BITS, interleave
from .clusters import Attributes
from .pairs import Axes
from .refine import fit_reflection

# Attribute differences at which the agreement score falls to exp(-1/2): colour (RGB distance), opacity, log-scales,
# and 1 - |cos| of the angle between a reflected distinct axis and its match's (0.1: about 25 degrees).
_COLOUR_SCALE = 0.15
_OPACITY_SCALE = 0.3
_LOG_SCALE_SCALE = 0.7
_AXIS_SCALE = 0.1
_OWN_SCORE = 0.5  # a Gaussian is matched when its own score reaches this ...
_REGION_SCORE = 0.4  # ... and the mean score of its voxel on its side this: chance matches are specks, not regions
_PRIOR_COUNT = 1.5  # unmatched pseudo-Gaussians added to every voxel: a lone matched Gaussian is a speck
_VOXEL_SPACINGS = 8.0  # voxel side, in typical spacings (about 9 Gaussians per voxel on a surface)
_CANDIDATES = 3  # nearest Gaussians across the plane compared with a reflection that its nearest does not match
_DEEP = 16  # nearest Gaussians searched for one across the plane, for reflections that land near it
_ICP_WIDEN = 3.0  # the plane refinement starts with this many times the tolerance
_ICP_SETTLED = 0.003  # ... and a stage ends once a step moves the plane less than this many typical spacings
_SAMPLE = 20_000  # Gaussians on which the typical spacing, match rates and plane refinement are estimated
# The plane's last polish climbs the matched share: tilts of this many radians and shifts of this share of the frame's
# radius first, halved whenever no move gains, down to the finest tilt.
_POLISH_TILT = math.radians(4.0)
_POLISH_SHIFT = 0.02
_POLISH_FINEST = math.radians(0.25)
_POLISH_TRIES = 240  # planes the polish scores at most: each costs a sampled match
_POLISH_GAIN_SE = 3.0  # ... and it is kept only when it matches this many standard errors more than where it began
_PARALLEL_QUERIES = 10_000
_TRAITS = 7  # scaled attributes per Gaussian: RGB, opacity, three sorted log-scales
_MORTON_SPAN = 2.0  # the order covers coordinates within this many frame radii; beyond, it clamps
_LN2 = math.log(2.0)
_CLOSE = 0.9  # geometric score of a match close enough to judge whether attributes agree here ...
_ALIKE = 0.5  # ... and the agreement above which they do


def _query(tree: cKDTree, points: np.ndarray, k: int, **kwargs: float) -> tuple[np.ndarray, np.ndarray]:
    """``tree.query`` on all cores for many points; on one for few, where starting threads costs more."""
    return tree.query(points, k=k, workers=-1 if len(points) >= _PARALLEL_QUERIES else 1, **kwargs)


@dataclass(frozen=True)
class Sides:
    """Membership of the working set for one plane (indices into the working set, on its device)."""

    left: Tensor  # [L] kept and reflected
    right: Tensor  # [R] dropped: covered by reflected left Gaussians


class Matcher:
    """Matches the sides of one working set for any plane; the KD-tree, spacings and voxels are built once.

    points [N, 3] in the normalised frame; ``tolerance`` in local spacings (a reflected Gaussian that far off scores
    one half); ``attribute_weight`` 0..1 is how much attribute agreement may scale the score.
    """

    def __init__(
        self, points: Tensor, attrs: Attributes, axes: Axes, *, tolerance: float, attribute_weight: float
    ) -> None:
        self.device = points.device
        self.tolerance = tolerance
        self.attribute_weight = attribute_weight
        p = points.detach().to(torch.float64).cpu().numpy()
        # Everything is held in a space-filling-curve order: the tree's leaves and the batches of queries then touch
        # memory in order, which makes building and querying several times faster than in the scene's order.
        # ``order`` [N] gives the working-set index of each position, ``rank`` [N] the position of each index.
        self.order = _morton_order(p)
        self.rank = np.empty_like(self.order)
        self.rank[self.order] = np.arange(len(self.order))
        # Per Gaussian, in one row so that a pair costs two gathers: its attributes scaled so that a unit distance is
        # one agreement scale (_TRAITS columns), then its distinct axis (3) for the orientation term. Gathered into
        # this order in one compiled pass.
        n = len(self.order)
        self.p = np.empty((n, 3))
        self.traits = np.empty((n, _TRAITS + 3), dtype=np.float32)
        self.round = np.empty(n, dtype=np.bool_)
        self.flat = np.empty(n, dtype=np.bool_)
        cpu = lambda t: t.detach().float().cpu().contiguous().numpy()  # noqa: E731
        _gather_kernel(
            self.order,
            p,
            cpu(attrs.rgb),
            cpu(attrs.opacity),
            cpu(attrs.log_scales),
            cpu(axes.u),
            axes.round.bool().cpu().numpy(),
            axes.flat.cpu().numpy(),
            np.array([_COLOUR_SCALE, _OPACITY_SCALE, _LOG_SCALE_SCALE], dtype=np.float32),
            self.p,
            self.traits,
            self.round,
            self.flat,
        )
        self.axis = self.traits[:, _TRAITS:]
        # Sliding-midpoint splits on ordered points build several times faster than median splits and query as fast.
        self.tree = cKDTree(self.p, balanced_tree=False, compact_nodes=False)
        rng = np.random.default_rng(0)
        self.sample = np.sort(self.rank[rng.choice(n, size=min(n, _SAMPLE), replace=False)])
        dist, _ = _query(self.tree, self.p[self.sample], k=min(2, n))
        nearest = dist.reshape(len(self.sample), -1)[:, -1]
        positive = nearest[nearest > 0]
        # Coincident Gaussians have no spacing; fall back to a tiny fraction of the frame (radius 1).
        self.typical = float(np.median(positive)) if positive.size else 1e-3
        voxel = _VOXEL_SPACINGS * self.typical
        # Voxels numbered in the order of their cell coordinates (x, then y, then z), as a sort of the keys would.
        self.voxel = np.empty(n, dtype=np.int64)
        counts = _voxel_kernel(self.p, voxel, self.voxel)
        self.voxels = counts.size
        # On a surface a voxel holds about (voxel / 2 spacing)^2 Gaussians: the local spacing follows from its count,
        # capped so that sparse Gaussians (floaters, clutter) do not get a tolerance wide enough to match by chance.
        local = 0.5 * voxel / np.sqrt(counts[self.voxel])
        self.spacing = np.clip(local, 0.5 * self.typical, 2.0 * self.typical)
        self.widest = float(self.spacing.max())
        # Whole voxels, in random order up to about _SAMPLE Gaussians, so that their region means are exact.
        shuffled = rng.permutation(counts.size)
        chosen = np.zeros(counts.size, dtype=bool)
        chosen[shuffled[: int(np.searchsorted(np.cumsum(counts[shuffled]), _SAMPLE)) + 1]] = True
        self.chance_sample = np.nonzero(chosen[self.voxel])[0]

    def sides(self, normal: Tensor, offset: float) -> Sides:
        """Membership for the plane normal.x = offset (normal [3] unit). The side with more matched Gaussians is
        kept (left); on a tie the side the normal points to."""
        n = normal.detach().to(torch.float64).cpu().numpy()
        d = _distances(self.p, n, offset)
        side = d > 0
        empty = torch.zeros(0, dtype=torch.long, device=self.device)
        if side.all() or not side.any():
            return Sides(empty, empty)
        matched, hit = self._matched(np.arange(len(d)), d, n, side)
        # A covered Gaussian needs a matched coverer, and a coverer a matched Gaussian to cover.
        cover = matched & matched[hit]
        keep_side = side if (cover & side).sum() >= (cover & ~side).sum() else ~side

        def t(mask: np.ndarray) -> Tensor:
            # Working-set indices in ascending order: marked in a mask of the working set, not sorted.
            marked = np.zeros(len(mask), dtype=np.bool_)
            marked[self.order[mask]] = True
            return torch.from_numpy(np.nonzero(marked)[0]).to(self.device)

        return Sides(t(cover & keep_side), t(cover & ~keep_side))

    def sampled_share(self, normal: Tensor, offset: float) -> tuple[float, float]:
        """Share of the Gaussians of random whole voxels (the ``chance_coverage`` sample) matched for the plane
        normal.x = offset, and its standard error (the voxels are the sampled units): an estimate from above of the
        plane's coverage (a covered Gaussian also needs its match matched), at the cost of a few percent of
        ``sides``."""
        idx = self.chance_sample
        if not idx.size:
            return 0.0, 0.0
        n = normal.detach().to(torch.float64).cpu().numpy()
        d = _distances(self.p, n, offset)
        matched, _ = self._matched(idx, d, n, d > 0)
        _, voxel = np.unique(self.voxel[idx], return_inverse=True)
        hits, counts = np.bincount(voxel, weights=matched), np.bincount(voxel)
        share = float(hits.sum() / counts.sum())
        # Ratio estimator over sampled clusters (voxels): the linearised variance of sum(hits) / sum(counts).
        error = float(np.sqrt(((hits - share * counts) ** 2).sum() * len(counts) / max(len(counts) - 1, 1)))
        return share, error / float(counts.sum())

    def chance_coverage(self, planes: int, seed: int) -> float:
        """Share of the Gaussians that random planes (random normals through random Gaussians) match, estimated on
        the Gaussians of random voxels: what any plane explains by chance here. Coarse or cluttered sets match much
        more by chance than finely sampled surfaces do."""
        gen = torch.Generator(HOST).manual_seed(seed)
        idx = self.chance_sample
        shares = []
        for _ in range(planes):
            drawn = torch.randn(3, generator=gen, dtype=torch.float64, device=HOST)
            n = torch.nn.functional.normalize(drawn, dim=0).numpy()
            offset = float(self.p[self.rank[int(torch.randint(self.p.shape[0], (1,), generator=gen, device=HOST))]] @ n)
            d = _distances(self.p, n, offset)
            matched, _ = self._matched(idx, d, n, d > 0)
            shares.append(float(matched.mean()) if matched.size else 0.0)
        return float(np.mean(shares)) if shares else 0.0

    def _matched(
        self, idx: np.ndarray, d: np.ndarray, n: np.ndarray, side: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Whether each of the Gaussians ``idx`` [M] (whole voxels) is matched, and the Gaussian [M] matching it."""
        score, hit, w, geo = self._scores(idx, d, n, side, k=1, weight=None)
        # With noise the twin need not be the very nearest: where the nearest is close but does not look alike, try
        # the next few (where the nearest is not close, the next few are farther still).
        retry = np.nonzero((score < _OWN_SCORE) & (geo >= 0.5))[0]
        if retry.size:
            score_r, hit_r, _, _ = self._scores(idx[retry], d, n, side, k=_CANDIDATES, weight=w)
            better = score_r > score[retry]
            score[retry[better]] = score_r[better]
            hit[retry[better]] = hit_r[better]
        region = self.voxel[idx] * 2 + side[idx]
        size = 2 * self.voxels
        mean = np.bincount(region, weights=score, minlength=size) / (np.bincount(region, minlength=size) + _PRIOR_COUNT)
        return (score >= _OWN_SCORE) & (mean[region] >= _REGION_SCORE), hit

    def _scores(
        self,
        idx: np.ndarray,
        d: np.ndarray,
        n: np.ndarray,
        side: np.ndarray,
        k: int,
        weight: float | None,
        widen: float = 1.0,
    ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
        """Best match score [M] of Gaussians ``idx`` [M] among their k nearest Gaussians across the plane (signed
        distances ``d`` [N] of all Gaussians to it, unit normal ``n`` [3], ``side`` [N] = d > 0), that
        Gaussian [M] (its own index where none), the attribute weight used (computed here when None), and the
        geometric score [M] of the best match. ``widen`` scales the tolerance."""
        reflected = np.empty((len(idx), 3))
        _reflect_kernel(self.p, idx, d, n, reflected)
        # Two tolerances out a match scores 1/16: nothing farther is worth finding.
        tolerance = widen * self.tolerance
        err, hit = self._other_side(reflected, idx, side, 2.0 * tolerance * self.widest, k)
        geo, agree = np.empty(err.shape), np.empty(err.shape)
        close, alike = _candidate_kernel(
            err, hit, idx, tolerance * self.spacing[idx], self.traits, self.round, n, geo, agree
        )
        if weight is None:
            weight = self.attribute_weight * alike / close if close else 0.0
        score, best_geo = np.empty(len(idx)), np.empty(len(idx))
        best_hit = np.empty(len(idx), dtype=np.int64)
        _best_kernel(geo, agree, hit, weight, score, best_hit, best_geo)
        return score, best_hit, weight, best_geo

    def refine(self, normal: Tensor, offset: float, iters: int) -> tuple[Tensor, float]:
        """Iterated closest points on (a sample of) the Gaussians that match for the current plane: pair each,
        reflected, with the nearest Gaussian of the other side, fit the plane to those pairs (``fit_reflection``),
        repeat. Only Gaussians that match take part, so that those of unrelated parts do not pull a local plane.
        The first half of the steps starts with a three times wider tolerance, narrowing, so that a start a few cells
        off still finds its pairs; the second half chooses its Gaussians again and keeps the tolerance. Either half
        ends early once a step moves the plane by a small fraction of the spacing (tilt in radians, the frame's
        radius being 1, plus offset): what is left is the jitter of the pairings, not a better plane.
        Returns the refined unit normal [3] (float64) and offset."""
        n = normal.detach().to(torch.float64).cpu().numpy()
        g = float(offset)
        wide = iters // 2
        for stage, steps in enumerate((wide, iters - wide)):
            start = _ICP_WIDEN if stage == 0 else 1.0
            d = _distances(self.p, n, g)
            score, _, _, _ = self._scores(self.sample, d, n, d > 0, k=1, weight=None, widen=start)
            idx = self.sample[score >= _OWN_SCORE]
            for it in range(steps):
                widen = max(1.0, start - (start - 1.0) * it / max(steps - 1, 1))
                new_n, new_g = self._icp_step(idx, n, g, widen * self.tolerance * self.spacing[idx])
                moved = math.acos(min(1.0, abs(float(new_n @ n)))) + abs(new_g - g)
                n, g = new_n, new_g
                if moved < _ICP_SETTLED * self.typical:
                    break
        return torch.from_numpy(n), g

    def polish(self, normal: Tensor, offset: float) -> tuple[Tensor, float]:
        """The plane near ``normal``, ``offset`` that matches the largest share of the sampled voxels
        (``sampled_share``), by a pattern search: tilts about two axes of the plane and shifts along its normal, the
        first that gains taken, the steps halved when none does. Iterated closest points settle where the pairs they
        found agree, which on independently reconstructed halves may be a few degrees off the plane that matches the
        most (on a trained lego, 5 degrees and 21% of its Gaussians matched against 50%): the share is what a
        membership is made of, so it has the last word, where it gains more than the sample's noise
        (``_POLISH_GAIN_SE``): on near twins the share is flat around the plane, whose closest points are more exact.
        Returns the unit normal [3] (float64) and offset."""
        start = (normal.detach().to(torch.float64).cpu(), float(offset))
        n = start[0].numpy()
        n = n / np.linalg.norm(n)
        g = float(offset)
        best, error = self.sampled_share(torch.from_numpy(n), g)
        first = best
        tilt, shift, tries = _POLISH_TILT, _POLISH_SHIFT, 0
        while tilt >= _POLISH_FINEST and tries < _POLISH_TRIES:
            u = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
            u /= np.linalg.norm(u)
            v = np.cross(n, u)
            t = math.tan(tilt)
            moves = [(n + t * u, g), (n - t * u, g), (n + t * v, g), (n - t * v, g), (n, g + shift), (n, g - shift)]
            for m, h in moves:
                m = m / np.linalg.norm(m)
                share, tries = self._share(m, h), tries + 1
                if share > best:
                    n, g, best = m, h, share
                    break
            else:
                tilt, shift = tilt / 2, shift / 2
        return (torch.from_numpy(n), g) if best > first + _POLISH_GAIN_SE * error else start

    def settle(self, normal: Tensor, offset: float, icp_iters: int) -> tuple[Tensor, float]:
        """The plane detection reports from a start near ``normal``, ``offset``: iterated closest points, the polish,
        and closest points again where the polish moved it (it finds the basin of the largest matched share, closest
        points its precise bottom). Returns the unit normal [3] (float64) and offset."""
        if icp_iters:
            normal, offset = self.refine(normal, offset, icp_iters)
        polished = self.polish(normal, offset)
        moved = polished[1] != offset or not torch.equal(polished[0], normal.to(polished[0]))
        return self.refine(*polished, icp_iters) if icp_iters and moved else polished

    def _share(self, n: np.ndarray, g: float) -> float:
        return self.sampled_share(torch.from_numpy(n), g)[0]

    def _icp_step(self, idx: np.ndarray, n: np.ndarray, g: float, tau: np.ndarray) -> tuple[np.ndarray, float]:
        """One refinement step on Gaussians ``idx`` with tolerances ``tau``; the plane unchanged when fewer than 8
        pairs are found."""
        if idx.size < 8:  # too few Gaussians match the current plane to pair, let alone fit one
            return n, g
        a = self.p[idx]
        d = _distances(a, n, g)
        err, hit = _query(self.tree, a - 2.0 * d[:, None] * n, k=1, distance_upper_bound=2.0 * float(tau.max()))
        hit = np.minimum(hit, self.p.shape[0] - 1)  # misses: index n, distance inf
        good = np.nonzero((err < 2.0 * tau) & (_distances(self.p[hit], n, g) * d < 0))[0]
        if good.size < 8:
            return n, g
        # Matches that look alike and lie close weigh most: clutter that happens to land near a surface does not.
        geo = np.exp(-_LN2 * (err[good] / tau[good]) ** 2)
        agree = self._agreement(idx[good], hit[good], n)
        w = self._attribute_trust(geo, agree)
        h = hit[good]
        return fit_reflection(a[good], self.p[h], self.axis[h], self.flat[h], geo * (1 - w + w * agree), n, g)

    def _other_side(
        self, reflected: np.ndarray, idx: np.ndarray, side: np.ndarray, cutoff: float, k: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """The k nearest Gaussians on the other side of the plane to the reflections [M, 3] of Gaussians ``idx``:
        distances [M, k] (inf beyond ``cutoff`` or on the own side) and indices [M, k]."""
        k = min(k, self.p.shape[0])
        err, hit = _query(self.tree, reflected, k=k, distance_upper_bound=cutoff)
        err, hit = err.reshape(-1, k), np.minimum(hit.reshape(-1, k), self.p.shape[0] - 1)  # misses: n, err inf
        own = side[idx]
        crossed = side[hit] != own[:, None]
        # A reflection lands |d| beyond the plane, so hits on its own side only happen near the plane (or where the
        # other side has nothing close); where none crossed, look deeper among the nearest for those that do.
        redo = np.nonzero(~crossed.any(axis=1) & np.isfinite(err[:, 0]))[0]
        err = np.where(crossed, err, np.inf)
        if redo.size:
            kk = min(_DEEP, self.p.shape[0])
            e, h = _query(self.tree, reflected[redo], k=kk, distance_upper_bound=cutoff)
            e, h = e.reshape(-1, kk), np.minimum(h.reshape(-1, kk), self.p.shape[0] - 1)
            e = np.where(side[h] != own[redo, None], e, np.inf)
            first = np.argsort(e, axis=1, kind="stable")[:, :k]
            err[redo] = np.take_along_axis(e, first, axis=1)
            hit[redo] = np.take_along_axis(h, first, axis=1)
        return err, hit

    def _attribute_trust(self, geo: np.ndarray, agree: np.ndarray) -> float:
        """Weight of attribute agreement in the score: ``attribute_weight`` times the share of the geometrically
        close matches (geo >= _CLOSE) whose attributes agree (agree > _ALIKE). Exact twins agree, so attributes then
        reject clutter that happens to land near a surface; the independently reconstructed halves of a real capture
        mostly do not (colours, sizes and orientations differ), and geometry alone decides."""
        close = geo >= _CLOSE
        if not close.any():
            return 0.0
        return self.attribute_weight * float((agree[close] > _ALIKE).mean())

    def _agreement(self, i: np.ndarray, j: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Soft agreement [M] in (0, 1] of Gaussians i [M] and j [M] as mirror images across a plane with unit normal
        ``n`` [3]: colour, opacity, sorted sizes, and the reflected distinct axis of i against that of j."""
        out = np.empty(len(i), dtype=np.float32)
        _agreement_kernel(self.traits, self.round, i.astype(np.int64), j.astype(np.int64), n.astype(np.float64), out)
        return out


@compiled
def _agree(traits, round_, a, b, n):  # noqa: ANN001, ANN202
    """``Matcher._agreement`` of one pair of Gaussians a, b (positions)."""
    e = 0.0
    for c in range(_TRAITS):
        t = float(traits[a, c]) - float(traits[b, c])
        e += t * t
    if not (round_[a] or round_[b]):  # round Gaussians have no axis to disagree
        dot, na, nb = 0.0, 0.0, 0.0
        for c in range(3):
            ua, ub = float(traits[a, _TRAITS + c]), float(traits[b, _TRAITS + c])
            dot += ua * ub
            na += ua * n[c]
            nb += ub * n[c]
        du = (1.0 - abs(dot - 2.0 * na * nb)) / _AXIS_SCALE  # (H u_a) . u_b, H = I - 2 n n^T
        e += du * du
    return math.exp(-0.5 * e)


@compiled
def _agreement_kernel(traits, round_, i, j, n, out):  # noqa: ANN001, ANN202
    """``Matcher._agreement`` into out [M] (float32): one fused pass instead of a dozen array-wide ones."""
    for r in range(i.shape[0]):
        out[r] = _agree(traits, round_, i[r], j[r], n)


@compiled_parallel
def _candidate_kernel(err, hit, idx, tau, traits, round_, n, geo, agree):  # noqa: ANN001, ANN202
    """Scores of the candidates (row r: Gaussian idx[r], column: the k nearest across the plane, err [M, k] inf
    where none): the geometric score into geo [M, k], 1/2 at tolerance tau [M], and the attribute agreement into
    agree [M, k]. A missing candidate scores 0 and becomes the Gaussian itself in hit [M, k] (in place). Returns how
    many candidates are close (geo >= _CLOSE), and how many of those agree (agree > _ALIKE)."""
    close, alike = 0, 0
    for r in prange(err.shape[0]):
        for c in range(err.shape[1]):
            if math.isinf(err[r, c]):
                hit[r, c] = idx[r]
                geo[r, c], agree[r, c] = 0.0, 0.0  # no agreement: it would weigh nothing
                continue
            t = err[r, c] / tau[r]
            g = math.exp(-_LN2 * t * t)
            a = _agree(traits, round_, idx[r], hit[r, c], n)
            geo[r, c], agree[r, c] = g, a
            if g >= _CLOSE:
                close += 1
                if a > _ALIKE:
                    alike += 1
    return close, alike


@compiled_parallel
def _best_kernel(geo, agree, hit, weight, score, best_hit, best_geo):  # noqa: ANN001, ANN202
    """Per row of the candidates (geo, agree, hit [M, k]) the best score geo (1 - w + w agree) into score [M], and
    that candidate's hit and geo into best_hit [M] and best_geo [M]; the first of equal ones."""
    for r in prange(geo.shape[0]):
        best = 0
        top = geo[r, 0] * (1.0 - weight + weight * agree[r, 0])
        for c in range(1, geo.shape[1]):
            s = geo[r, c] * (1.0 - weight + weight * agree[r, c])
            if s > top:
                best, top = c, s
        score[r], best_hit[r], best_geo[r] = top, hit[r, best], geo[r, best]


def _distances(p: np.ndarray, n: np.ndarray, offset: float) -> np.ndarray:
    """Signed distances [N] of points p [N, 3] to the plane n.x = offset, in one compiled pass (numpy's threaded
    matrix-vector product stalls on a busy machine)."""
    out = np.empty(p.shape[0])
    _distance_kernel(np.ascontiguousarray(p, dtype=np.float64), np.asarray(n, dtype=np.float64), float(offset), out)
    return out


@compiled_parallel
def _gather_kernel(order, p, rgb, opacity, log_scales, u, round_, flat, scales, p_out, traits, round_out, flat_out):  # noqa: ANN001, ANN202, PLR0913
    """Row r of the outputs from Gaussian order[r]: its point, its traits (colour, opacity and log-scales divided by
    scales [3] in float32, then its axis u), whether it is round and flat."""
    for r in prange(order.shape[0]):
        s = order[r]
        for c in range(3):
            p_out[r, c] = p[s, c]
            traits[r, c] = rgb[s, c] / scales[0]
            traits[r, 4 + c] = log_scales[s, c] / scales[2]
            traits[r, _TRAITS + c] = u[s, c]
        traits[r, 3] = opacity[s] / scales[1]
        round_out[r] = round_[s]
        flat_out[r] = flat[s]


@compiled_parallel
def _reflect_kernel(p, idx, d, n, out):  # noqa: ANN001, ANN202
    """out [M, 3] = p[idx] - 2 d[idx] n: the reflections of points idx [M] across the plane of normal n [3] (d [N]
    their signed distances to it)."""
    for r in prange(idx.shape[0]):
        i = idx[r]
        for c in range(3):
            out[r, c] = p[i, c] - 2.0 * d[i] * n[c]


@compiled
def _voxel_kernel(p, voxel, label):  # noqa: ANN001, ANN202
    """The voxel (side ``voxel``) of each point p [N, 3] into label [N], voxels numbered in the order of their cell
    coordinates (clamped to +-2^20); returns the points per voxel [V]. The cells, less their minimum, are packed into
    as few bits as they need and sorted by LSD radix sort, 16 bits a pass (two passes for most scenes)."""
    n = p.shape[0]
    cells = np.empty((n, 3), dtype=np.int64)
    lo = np.full(3, 2**20, dtype=np.int64)
    hi = np.full(3, -(2**20), dtype=np.int64)
    for r in range(n):
        for c in range(3):
            cell = min(max(math.floor(p[r, c] / voxel), -(2**20)), 2**20 - 1)
            cells[r, c] = cell
            lo[c] = min(lo[c], cell)
            hi[c] = max(hi[c], cell)
    bits = np.zeros(3, dtype=np.int64)
    for c in range(3):
        while (hi[c] - lo[c]) >> bits[c]:
            bits[c] += 1
    key = np.empty(n, dtype=np.int64)
    for r in range(n):
        key[r] = (((cells[r, 0] - lo[0]) << bits[1]) | (cells[r, 1] - lo[1])) << bits[2] | (cells[r, 2] - lo[2])
    order = np.arange(n)
    spare = np.empty(n, dtype=np.int64)
    shift = 0
    while shift < bits[0] + bits[1] + bits[2]:
        counts = np.zeros((1 << 16) + 1, dtype=np.int64)
        for r in range(n):
            counts[((key[r] >> shift) & 0xFFFF) + 1] += 1
        for d in range(1, counts.shape[0]):
            counts[d] += counts[d - 1]
        for r in range(n):
            digit = (key[order[r]] >> shift) & 0xFFFF
            spare[counts[digit]] = order[r]
            counts[digit] += 1
        order, spare = spare, order
        shift += 16
    sizes = np.zeros(n, dtype=np.int64)
    v = -1
    for r in range(n):
        if r == 0 or key[order[r]] != key[order[r - 1]]:
            v += 1
        label[order[r]] = v
        sizes[v] += 1
    return sizes[: v + 1]


@compiled_parallel
def _distance_kernel(p, n, offset, out):  # noqa: ANN001, ANN202
    """out [N] = p [N, 3] . n [3] - offset."""
    for r in prange(p.shape[0]):
        out[r] = p[r, 0] * n[0] + p[r, 1] * n[1] + p[r, 2] * n[2] - offset


def _morton_order(p: np.ndarray) -> np.ndarray:
    """Indices [N] that sort points p [N, 3] (normalised frame) along a Morton (Z-order) curve: nearby points end
    up mostly nearby in the order. Each coordinate is cut into 2^AXIS_BITS cells over +-_MORTON_SPAN."""
    cells = 1 << AXIS_BITS
    scale = cells / (2.0 * _MORTON_SPAN)
    at = np.clip((np.asarray(p, dtype=np.float64) + _MORTON_SPAN) * scale, 0, cells - 1).astype(np.int64)
    return np.argsort(interleave(at))
