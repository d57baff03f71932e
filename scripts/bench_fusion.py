#!/usr/bin/env python
"""Milliseconds per fusion step with a ~1 M-surfel map: Taichi kernels against vectorised NumPy.

    .venv/bin/python scripts/bench_fusion.py [--arch cpu] [--surfels 1000000] [--steps 10] [--sizes 320x240,640x480]

For each resolution: fuse frames of the synthetic sequence (noise on) with the Taichi mapper until the
map holds ``--surfels`` surfels, copy that map into a NumPy implementation of the same step (below:
project, filter passes 1 and 2 in the configured order (Keller's "compatible" by default), the
nearest-depth index map, merge, add with the covered-pixel test, remove, with the same thresholds),
then run the next ``--steps`` frames through both, each on its own copy, and print the median
milliseconds per stage and the ratio, measured in the same run. The first Taichi step of each size
(kernel compilation) is not timed, and each Taichi step starts 0.2 s after the NumPy one, once
OpenBLAS's threads have stopped spinning. Freed memory is kept for reuse (``ti_fusion.timing.keep_freed_memory``)
so that NumPy's large temporaries do not page-fault afresh at every step.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

STAGES = ("project", "filter", "merge", "add", "remove")
BLAS_SETTLE_S = 0.2  # pause after each NumPy step (see bench_size)


class NumpyFusion:
    """The fusion step of ``ti_fusion.fusion.SurfelMapper`` in vectorised NumPy (float32 arrays)."""

    def __init__(self, data: dict, cfg, capacity: int):
        self.cfg = cfg
        self.n = len(data["position"])
        self.a = {}
        for name, arr in data.items():
            full = np.zeros((capacity,) + arr.shape[1:], arr.dtype)
            full[: self.n] = arr
            self.a[name] = full

    def integrate(self, vertex, normal, depth, colour, pose, K, frame) -> dict:
        cfg, a, n = self.cfg, self.a, self.n
        H, W = depth.shape
        ms = {}
        t0 = time.perf_counter()
        # project + filter pass 1 + nearest surfel per pixel
        inv = np.linalg.inv(pose)
        Rw, tw = inv[:3, :3].astype(np.float32), inv[:3, 3].astype(np.float32)
        pc = a["position"][:n] @ Rw.T + tw
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uf = K.fx * pc[:, 0] / z + K.cx + 0.5
            vf = K.fy * pc[:, 1] / z + K.cy + 0.5
            inside = (z > 0) & (uf >= 0) & (uf < W) & (vf >= 0) & (vf < H)
        ids = np.flatnonzero(inside)
        pix = vf[ids].astype(np.int64) * W + uf[ids].astype(np.int64)
        zi = z[ids]
        R, t = pose[:3, :3].astype(np.float32), pose[:3, 3].astype(np.float32)
        q = vertex.reshape(-1, 3)
        nq = normal.reshape(-1, 3)
        valid = (q[:, 2] > 0) & np.any(nq != 0, axis=1)
        cos_thr = math.cos(math.radians(cfg.normal_threshold_deg))
        if cfg.association == "compatible":
            # Keller's order: filter pass 2 for every surfel of pass 1, in the world frame (the frame's
            # measurements turned once, as the kernels' world_measurements), then the nearest that passed
            q_world = q @ R.T + t
            n_world = nq @ R.T
            d = a["position"][ids] - q_world[pix]
            ok = valid[pix] & (np.einsum("ij,ij->i", d, d) <= cfg.dist_threshold ** 2) & \
                (np.einsum("ij,ij->i", a["normal"][ids], n_world[pix]) >= cos_thr)
            ids, pix, zi = ids[ok], pix[ok], zi[ok]
        # the kernels' two passes: nearest depth per pixel, then the smallest index at that depth
        # (np.minimum.at is NumPy's unbuffered scatter-min: ~10× faster here than sorting by depth)
        nearest = np.full(H * W, np.inf, np.float32)
        np.minimum.at(nearest, pix, zi)
        won = zi == nearest[pix]
        index = np.full(H * W, np.iinfo(np.int64).max, np.int64)
        np.minimum.at(index, pix[won], ids[won])
        index[index == np.iinfo(np.int64).max] = -1
        t1 = time.perf_counter()
        ms["project"] = (t1 - t0) * 1e3
        # filter pass 2 (in the projection above for Keller's order)
        cand = np.flatnonzero((index >= 0) & valid)
        i = index[cand]
        if cfg.association == "compatible":
            px, qw, nw = cand, q_world[cand], n_world[cand]
        else:
            qw, nw = q[cand] @ R.T + t, nq[cand] @ R.T
            ok = (np.linalg.norm(qw - a["position"][i], axis=1) <= cfg.dist_threshold) & \
                 (np.einsum("ij,ij->i", nw, a["normal"][i]) >= cos_thr)
            px, i, qw, nw = cand[ok], i[ok], qw[ok], nw[ok]
        t2 = time.perf_counter()
        ms["filter"] = (t2 - t1) * 1e3
        # merge
        vv, uu = px // W, px % W
        alpha = self._alpha(uu, vv, K, q[px, 2])[:, None]
        w = a["weight"][i][:, None]
        a["position"][i] = (w * a["position"][i] + alpha * qw) / (w + alpha)
        nn = w * a["normal"][i] + alpha * nw
        a["normal"][i] = nn / np.linalg.norm(nn, axis=1, keepdims=True)
        rgb = colour.reshape(-1, 3).astype(np.float32)
        a["colour"][i] = (w * a["colour"][i] + alpha * rgb[px]) / (w + alpha)
        a["weight"][i] = (w + alpha)[:, 0]
        a["radius"][i] = np.minimum(a["radius"][i], self._radius(q[px, 2], nq[px, 2], K))
        a["t_updated"][i] = frame
        t3 = time.perf_counter()
        ms["merge"] = (t3 - t2) * 1e3
        # add (skipping pixels covered by the disc of a surfel merged at a neighbouring pixel)
        assoc = np.full(H * W, -1, np.int64)
        assoc[px] = i
        new = np.flatnonzero(valid & (assoc < 0))
        if cfg.skip_covered:
            new = new[~self._covered(new, assoc.reshape(H, W), q, nq, R, t, cos_thr)]
        k = len(new)
        sl = slice(n, n + k)
        a["position"][sl] = q[new] @ R.T + t
        a["normal"][sl] = nq[new] @ R.T
        a["colour"][sl] = rgb[new]
        a["weight"][sl] = self._alpha(new % W, new // W, K, q[new, 2])
        a["radius"][sl] = self._radius(q[new, 2], nq[new, 2], K)
        a["t_created"][sl] = frame
        a["t_updated"][sl] = frame
        n += k
        t4 = time.perf_counter()
        ms["add"] = (t4 - t3) * 1e3
        # remove unstable surfels and compact as the kernels do: the k-th survivor at or above the new count
        # m moves into the k-th hole below m, so only the holes are written, not the whole map (copying every
        # survivor, as a boolean mask does, made this stage 6x slower at 320×240)
        drop = (a["weight"][:n] < cfg.unstable_weight) & (frame - a["t_updated"][:n] >= cfg.unstable_age)
        removed = int(np.count_nonzero(drop))
        if removed:
            m = n - removed
            holes = np.flatnonzero(drop[:m])
            movers = m + np.flatnonzero(~drop[m:])
            for arr in a.values():
                arr[holes] = arr[movers]
            n = m
        self.n = n
        ms["remove"] = (time.perf_counter() - t4) * 1e3
        return ms

    def _covered(self, pixels, assoc, q, nq, R, t, cos_thr) -> np.ndarray:
        a, (H, W) = self.a, assoc.shape
        vc, uc = pixels // W, pixels % W
        qw = q[pixels] @ R.T + t
        nw = nq[pixels] @ R.T
        covered = np.zeros(len(pixels), bool)
        for dv in (-1, 0, 1):
            for du in (-1, 0, 1):
                if dv == 0 and du == 0:
                    continue
                y, x = vc + dv, uc + du
                inside = (y >= 0) & (y < H) & (x >= 0) & (x < W)
                j = np.full(len(pixels), -1, np.int64)
                j[inside] = assoc[y[inside], x[inside]]
                k = np.flatnonzero((j >= 0) & ~covered)
                jk = j[k]
                d = qw[k] - a["position"][jk]
                n = a["normal"][jk]
                along = np.einsum("ij,ij->i", n, d)
                hit = (np.abs(along) <= self.cfg.dist_threshold) & \
                      (np.einsum("ij,ij->i", d, d) - along ** 2 <= a["radius"][jk] ** 2) & \
                      (np.einsum("ij,ij->i", n, nw[k]) >= cos_thr)
                covered[k[hit]] = True
        return covered

    def _alpha(self, u, v, K, z):
        a = np.ones(len(u), np.float32)
        if self.cfg.confidence_weighting:
            g2 = ((u - K.cx) ** 2 + (v - K.cy) ** 2) / (K.cx ** 2 + K.cy ** 2)
            a = np.exp(-g2 / (2 * self.cfg.confidence_sigma ** 2)).astype(np.float32)
        if self.cfg.depth_weighting:
            from ti_fusion.kernels import fusion as F

            s = F.NOISE_1M / (F.NOISE_A + F.NOISE_B * (z - F.NOISE_Z0) ** 2)
            a = a * np.minimum(s * s, F.DEPTH_WEIGHT_MAX).astype(np.float32)
        return a

    @staticmethod
    def _radius(z, nz, K):
        return (math.sqrt(2.0) * z / (K.fx * np.maximum(np.abs(nz), 0.2))).astype(np.float32)


def bench_size(width: int, height: int, target: int, steps: int) -> dict:
    from ti_fusion.config import FusionConfig, SynthConfig
    from ti_fusion.fusion import SurfelMapper
    from ti_fusion.kernels.maps import FrameMaps
    from ti_fusion.synthetic import SyntheticSequence
    from ti_fusion.timing import StageTimer

    fx = 525.0 * width / 640.0
    seq = SyntheticSequence(SynthConfig(frames=600, width=width, height=height, fx=fx, noise=True))
    K = seq.intrinsics
    cfg = FusionConfig(level=0)  # the step at this resolution (the SLAM default fuses 640×480 input at 320×240)
    mapper = SurfelMapper(cfg)
    maps = FrameMaps(height, width, levels=1)
    frame = 0
    while mapper.count < target:  # build the map along the camera path
        depth, colour = seq.frame(frame)
        maps.compute(depth, K)
        mapper.integrate(maps, colour, seq.poses[frame], frame)
        frame += 1
    print(f"  {width}×{height}: map of {mapper.count:,} surfels after {frame} frames", flush=True)
    ref = NumpyFusion(mapper.to_numpy(), cfg, capacity=mapper.map.capacity)
    timer = StageTimer()
    numpy_ms: dict[str, list[float]] = {s: [] for s in STAGES}
    counts = []
    for k in range(steps + 1):
        i = frame + k
        depth, colour = seq.frame(i)
        maps.compute(depth, K)
        stats = mapper.integrate(maps, colour, seq.poses[i], frame + k, timer)
        ms = ref.integrate(maps.vertex[0].to_numpy(), maps.normal[0].to_numpy(), depth, colour, seq.poses[i], K,
                           frame + k)
        # NumPy's matrix products wake OpenBLAS's worker threads, which spin for tens of ms afterwards: the
        # next Taichi step would share the cores with them. Wait until they sleep again.
        time.sleep(BLAS_SETTLE_S)
        if k > 0:  # the first Taichi step compiles the kernels
            for s in STAGES:
                numpy_ms[s].append(ms[s])
        counts.append((stats.surfels, ref.n))
    taichi = timer.summary(skip_first=1)
    row = {"size": f"{width}×{height}", "surfels": counts[0][0],
           "taichi": {s: taichi[s]["median"] for s in STAGES},
           "numpy": {s: float(np.median(numpy_ms[s])) for s in STAGES},
           "final_counts": counts[-1]}
    row["taichi"]["step"] = sum(row["taichi"][s] for s in STAGES)
    row["numpy"]["step"] = sum(row["numpy"][s] for s in STAGES)
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    parser.add_argument("--arch", default="cpu", help="Taichi backend: cpu | vulkan | cuda | auto")
    parser.add_argument("--surfels", type=int, default=1_000_000, help="map size before the timed steps")
    parser.add_argument("--steps", type=int, default=10, help="timed steps per size (after one warm-up)")
    parser.add_argument("--sizes", default="320x240,640x480", help="comma-separated WxH")
    args = parser.parse_args()
    from ti_fusion.timing import keep_freed_memory

    kept = keep_freed_memory()  # NumPy at its best: see keep_freed_memory

    from ti_fusion.backend import init_backend

    backend = init_backend(args.arch)
    print(f"backend: {backend.arch}; map ≈ {args.surfels:,} surfels; {args.steps} timed steps per size; freed memory "
          f"{'kept (glibc): NumPy timed at its best' if kept else 'returned to the system (not glibc)'}", flush=True)
    rows = []
    for size in args.sizes.split(","):
        w, h = (int(x) for x in size.lower().split("x"))
        rows.append(bench_size(w, h, args.surfels, args.steps))

    cols = (*STAGES, "step")
    print()
    print(f"{'size':<9} {'surfels':>9}  {'impl':<7}" + "".join(f"{c:>9}" for c in cols))
    for r in rows:
        print(f"{r['size']:<9} {r['surfels']:>9,}  {'taichi':<7}" + "".join(f"{r['taichi'][c]:9.2f}" for c in cols))
        print(f"{'':<9} {'':>9}  {'numpy':<7}" + "".join(f"{r['numpy'][c]:9.2f}" for c in cols))
        print(f"{'':<9} {'':>9}  {'ratio':<7}" + "".join(
            f"{r['numpy'][c] / r['taichi'][c]:8.1f}×" if r["taichi"][c] >= 0.05 else f"{'-':>9}" for c in cols))
        t, n = r["final_counts"]
        print(f"{'':<9} surfels after the timed steps: taichi {t:,}, numpy {n:,}")
    print("\nms per stage: median over the timed steps (Taichi stages synchronised with ti.sync()).")
    from ti_fusion.config import FusionConfig

    if FusionConfig().association == "compatible":
        print("With Keller's order (fusion.association = compatible) the Taichi step runs filter pass 2 inside its "
              "projection kernel, so its filter stage is empty: compare the step totals.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
