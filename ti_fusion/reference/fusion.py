"""The fusion step of ``SurfelMapper`` in vectorised NumPy, and the map it is compared on.

``NumpyFusion`` computes the kernels' step on float32 arrays, as the map stores them (the same
surfels merged, appended, covered and removed, in the same places of the map): the tests compare it
with the kernels and ``scripts/bench_fusion.py`` times it as their baseline. ``build_map`` builds the
setting of both, a map fused by the kernels along the synthetic sequence; ``matching_rows`` says how
much of one map agrees with another.
"""

from __future__ import annotations

import math

import numpy as np

from ti_fusion.kernels.surfels import ATTRIBUTES
from ti_fusion.timing import Stopwatch


def _dot(a, b):
    """Row-wise dot products of two (m, 3) arrays, a column at a time: the sums of np.einsum("ij,ij->i", a, b)
    (and of np.linalg.norm), in the same order, without their per-row overhead."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _put_rows(arr, idx, rows):
    """arr[idx] = rows, a column at a time for an (n, 3) array (faster than assigning rows of three)."""
    if arr.ndim == 1:
        arr[idx] = rows
    else:
        for c in range(arr.shape[1]):
            arr[:, c][idx] = rows[:, c]


def _rigid(p, R, t):
    """p @ R.T + t for (m, 3) rows, t added a column at a time: broadcast over rows of three, the addition
    costs more than the product."""
    out = p @ R.T
    for c in range(3):
        out[:, c] += t[c]
    return out


class NumpyFusion:
    """The fusion step of ``ti_fusion.mapping.mapper.SurfelMapper`` in vectorised NumPy (float32 arrays).

    NumPy at its best, so that the ratio to the kernels is an honest one; the maps it makes are bit for bit
    those of the plain formulation (fancy indexing, boolean masks, einsum, the whole map at once), with the
    forms that were fastest on this step:
    - rows of the (m, 3) arrays are gathered with ``np.take(arr, idx, axis=0)`` rather than ``arr[idx]``,
      subsets are selected through index lists (``np.flatnonzero``) rather than boolean masks, dot products
      and row assignments go a column at a time (``_dot``, ``_put_rows``);
    - the projection runs over blocks of surfels (``BLOCK``), so that its temporaries stay in the cache;
    - of the tests that decide together, the selective one (the normal test) runs first and the others only
      on what it keeps;
    - as in the kernels, the radial confidence is a per-pixel table computed once, the coverage test reads
      the merged surfels from the merge's results rather than from the map, and the map's memory is
      written once when it is allocated.
    """

    # Surfels per block of the projection: on the whole map at once, its temporaries (tens of MB) leave the
    # cache and, growing with the map, page-fault afresh at each step
    BLOCK = 1 << 16
    # Keller's radial confidence per pixel, by (shape, cx, cy, σ): computed once, as the kernels' fill_radial
    _radial_tables: dict = {}

    def __init__(self, data: dict, cfg, capacity: int):
        self.cfg = cfg
        self.n = len(data["position"])
        self.a = {}
        for name, arr in data.items():
            # zeros written now, not np.zeros, whose pages are mapped at their first write: the surfels added at
            # each step would page-fault in the timed add stage, while the kernels' fields are resident from
            # their allocation
            full = np.empty((capacity,) + arr.shape[1:], arr.dtype)
            full[: self.n] = arr
            full[self.n:] = 0
            self.a[name] = full

    def integrate(self, vertex, normal, depth, color, pose, K, frame) -> dict:
        cfg, a, n = self.cfg, self.a, self.n
        H, W = depth.shape
        ms = {}
        watch = Stopwatch()
        # project + filter pass 1 + nearest surfel per pixel
        inv = np.linalg.inv(pose)
        Rw, tw = inv[:3, :3].astype(np.float32), inv[:3, 3].astype(np.float32)
        R, t = pose[:3, :3].astype(np.float32), pose[:3, 3].astype(np.float32)
        q = vertex.reshape(-1, 3)
        nq = normal.reshape(-1, 3)
        # positive depth and a non-zero normal (three column tests: np.any(nq != 0, axis=1) is much slower)
        valid = (q[:, 2] > 0) & ((nq[:, 0] != 0) | (nq[:, 1] != 0) | (nq[:, 2] != 0))
        cos_thr = math.cos(math.radians(cfg.normal_threshold_deg))
        # the frame's measurements in the world frame, as the kernels' world_measurements
        q_world = _rigid(q, R, t)
        n_world = nq @ R.T
        found = [(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))]  # (an empty map)
        for s in range(0, n, self.BLOCK):
            # the camera-frame coordinates as three contiguous rows (the same sums as position @ Rw.T + tw): on
            # (m, 3) rows the product and the projection below are several times slower (tw broadcast over rows
            # of three, strided columns)
            x, y, z = Rw @ a["position"][s:min(s + self.BLOCK, n)].T + tw[:, None]
            with np.errstate(divide="ignore", invalid="ignore"):
                uf = K.fx * x / z + K.cx + 0.5
                vf = K.fy * y / z + K.cy + 0.5
                inside = (z > 0) & (uf >= 0) & (uf < W) & (vf >= 0) & (vf < H)
            ids = np.flatnonzero(inside)
            pix = vf[ids].astype(np.int64) * W + uf[ids].astype(np.int64)
            zi = z[ids]
            ids += s
            # Keller's order: filter pass 2 for every surfel of pass 1, in the world frame, then (below) the
            # nearest that passed. The normal test first, the distance for the surfels it keeps
            ok = np.flatnonzero(_dot(np.take(a["normal"], ids, axis=0), np.take(n_world, pix, axis=0)) >= cos_thr)
            ids, pix, zi = ids[ok], pix[ok], zi[ok]
            d = np.take(a["position"], ids, axis=0) - np.take(q_world, pix, axis=0)
            ok = np.flatnonzero(valid[pix] & (_dot(d, d) <= cfg.dist_threshold ** 2))
            ids, pix, zi = ids[ok], pix[ok], zi[ok]
            found.append((ids, pix, zi))
        ids, pix, zi = (np.concatenate(v) for v in zip(*found))
        # the kernels' two passes: nearest depth per pixel, then the smallest index at that depth (with
        # np.minimum.at, NumPy's unbuffered scatter-min, far faster here than sorting by pixel then depth)
        nearest = np.full(H * W, np.inf, np.float32)
        np.minimum.at(nearest, pix, zi)
        won = np.flatnonzero(zi == nearest[pix])
        index = np.full(H * W, np.iinfo(np.int64).max, np.int64)
        np.minimum.at(index, pix[won], ids[won])
        index[index == np.iinfo(np.int64).max] = -1
        # the associated pixels in pixel order, not in index order as the kernels' merge: the frame's arrays are
        # then read in order, and so are the coverage test's reads of the merged surfels
        px = np.flatnonzero((index >= 0) & valid)
        i = index[px]
        qw, nw = np.take(q_world, px, axis=0), np.take(n_world, px, axis=0)
        ms["project"] = watch.lap()
        # merge
        rgb = color.reshape(-1, 3)  # uint8: only the rows used are converted
        alpha = self._alpha(px, q[:, 2][px], K, (H, W))[:, None]
        w = a["weight"][i][:, None]
        wa = w + alpha
        p_new = (w * np.take(a["position"], i, axis=0) + alpha * qw) / wa
        nn = w * np.take(a["normal"], i, axis=0) + alpha * nw
        n_new = nn / np.sqrt(_dot(nn, nn))[:, None]
        r_new = np.minimum(a["radius"][i], self._radius(q[:, 2][px], nq[:, 2][px], K))
        _put_rows(a["position"], i, p_new)
        _put_rows(a["normal"], i, n_new)
        _put_rows(a["color"], i, (w * np.take(a["color"], i, axis=0) +
                                  alpha * np.take(rgb, px, axis=0).astype(np.float32)) / wa)
        a["weight"][i] = wa[:, 0]
        a["radius"][i] = r_new
        a["t_updated"][i] = frame
        ms["merge"] = watch.lap()
        # add (skipping pixels covered by the disc of a surfel merged at a neighbouring pixel)
        merged_at = np.full(H * W, -1, np.int64)  # the surfel merged at each pixel, as a row of p_new, n_new, r_new
        merged_at[px] = np.arange(len(px))
        new = np.flatnonzero(valid & (merged_at < 0))
        qw, nw = np.take(q_world, new, axis=0), np.take(n_world, new, axis=0)  # turned in the projection
        if cfg.skip_covered:
            keep = np.flatnonzero(~self._covered(new, qw, nw, merged_at.reshape(H, W), p_new, n_new, r_new, cos_thr))
            new, qw, nw = new[keep], np.take(qw, keep, axis=0), np.take(nw, keep, axis=0)
        k = len(new)
        sl = slice(n, n + k)
        a["position"][sl] = qw
        a["normal"][sl] = nw
        a["color"][sl] = np.take(rgb, new, axis=0)
        a["weight"][sl] = self._alpha(new, q[:, 2][new], K, (H, W))
        a["radius"][sl] = self._radius(q[:, 2][new], nq[:, 2][new], K)
        a["t_created"][sl] = frame
        a["t_updated"][sl] = frame
        n += k
        ms["add"] = watch.lap()
        # remove unstable surfels and compact as the kernels do: the k-th survivor at or above the new count
        # m moves into the k-th hole below m, so only the holes are written, not the whole map (as copying
        # every survivor through a boolean mask would)
        drop = (a["weight"][:n] < cfg.unstable_weight) & (a["t_updated"][:n] <= frame - cfg.unstable_age)
        removed = int(np.count_nonzero(drop))
        if removed:
            m = n - removed
            holes = np.flatnonzero(drop[:m])
            movers = m + np.flatnonzero(~drop[m:])
            for arr in a.values():
                _put_rows(arr, holes, np.take(arr, movers, axis=0))
            n = m
        self.n = n
        ms["remove"] = watch.lap()
        return ms

    def _covered(self, pixels, qw, nw, merged_at, position, normal, radius, cos_thr) -> np.ndarray:
        """Whether the point qw (normal nw), world frame, of each pixel lies on the disc of a surfel merged at
        one of its 8 neighbours. ``merged_at``: H×W, the row of ``position``, ``normal``, ``radius`` (the merged
        surfels as the merge left them) of the surfel merged at each pixel, -1 where none."""
        H, W = merged_at.shape
        # a border of -1 (no surfel) around the image: the neighbours of edge pixels need no bounds test
        padded = np.full((H + 2, W + 2), -1, np.int64)
        padded[1:-1, 1:-1] = merged_at
        padded = padded.ravel()
        centre = (pixels // W + 1) * (W + 2) + pixels % W + 1
        covered = np.zeros(len(pixels), bool)
        for dv in (-1, 0, 1):
            for du in (-1, 0, 1):
                if dv == 0 and du == 0:
                    continue
                j = padded[centre + dv * (W + 2) + du]
                k = np.flatnonzero((j >= 0) & ~covered)
                # the normal test first, the disc for the pixels it keeps
                k = k[_dot(np.take(normal, j[k], axis=0), np.take(nw, k, axis=0)) >= cos_thr]
                jk = j[k]
                d = np.take(qw, k, axis=0) - np.take(position, jk, axis=0)
                along = _dot(np.take(normal, jk, axis=0), d)
                hit = (np.abs(along) <= self.cfg.dist_threshold) & (_dot(d, d) - along ** 2 <= radius[jk] ** 2)
                covered[k[hit]] = True
        return covered

    def _alpha(self, pixels, z, K, shape):
        """Measurement weights of the given pixels (flat indices, depths z): 1 or Keller's radial confidence,
        times the depth weight."""
        if self.cfg.confidence_weighting:
            a = self._radial(K, shape)[pixels]
        else:
            a = np.ones(len(pixels), np.float32)
        if self.cfg.depth_weighting:
            from ti_fusion.kernels.fusion import DEPTH_WEIGHT_MAX
            from ti_fusion.sensor import SIGMA_1M, depth_sigma

            s = SIGMA_1M / depth_sigma(z)
            a = a * np.minimum(s * s, DEPTH_WEIGHT_MAX).astype(np.float32)
        return a

    def _radial(self, K, shape):
        """Keller's radial confidence exp(−γ²/2σ²) of every pixel (flat index), γ its distance from the image
        centre over the largest such distance."""
        sigma = self.cfg.confidence_sigma
        key = (shape, K.cx, K.cy, sigma)
        if key not in self._radial_tables:
            v, u = np.divmod(np.arange(shape[0] * shape[1]), shape[1])
            g2 = ((u - K.cx) ** 2 + (v - K.cy) ** 2) / (K.cx ** 2 + K.cy ** 2)
            self._radial_tables[key] = np.exp(-g2 / (2 * sigma ** 2)).astype(np.float32)
        return self._radial_tables[key]

    @staticmethod
    def _radius(z, nz, K):
        return (math.sqrt(2.0) * z / (K.fx * np.maximum(np.abs(nz), 0.2))).astype(np.float32)


def build_map(width: int, height: int, target: int, cfg):
    """Fuse frames of the synthetic sequence (noise on) at width×height until the map holds ``target``
    surfels: (mapper, frame maps, sequence, index of the next frame)."""
    from ti_fusion.config import PyramidConfig, SynthConfig
    from ti_fusion.mapping.mapper import SurfelMapper
    from ti_fusion.kernels.pyramid import FramePyramid
    from ti_fusion.synthetic.scene import SyntheticSequence

    fx = 525.0 * width / 640.0
    seq = SyntheticSequence(SynthConfig(frames=600, width=width, height=height, fx=fx, noise=True))
    K = seq.intrinsics
    mapper = SurfelMapper(cfg)
    pyramid = FramePyramid(PyramidConfig(depth_smooth_radius=0), height, width, levels=1)
    frame = 0
    while mapper.count < target:  # build the map along the camera path
        depth, color = seq.frame(frame)
        pyramid.compute(depth, K)
        mapper.integrate(pyramid, color, seq.poses[frame], frame)
        frame += 1
    return mapper, pyramid, seq, frame


def matching_rows(a: dict, b: dict, tol: float = 1e-4) -> float:
    """Fraction of surfels whose every attribute agrees to ``tol`` (relative to the attribute's scale)."""
    same = np.ones(len(a["position"]), bool)
    for name in ATTRIBUTES:
        x, y = a[name].astype(np.float64), b[name].astype(np.float64)
        err = np.abs(x - y).reshape(len(x), -1).max(axis=1)
        same &= err <= tol * max(1.0, float(np.abs(y).max()))
    return float(same.mean())
