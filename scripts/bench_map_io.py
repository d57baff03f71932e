#!/usr/bin/env python
"""Saving and loading a map of ~1 M surfels: seconds each, and bytes per surfel, against the targets.

    .venv/bin/python scripts/bench_map_io.py [--surfels 1000000] [--keyframes-from RUN_OR_MAP] [--repeat 3]

Builds a saved map of ``--surfels`` random surfels (every attribute, as the run keeps them) with the keyframes,
place recognition and pose graph of a real run's saved map (``--keyframes-from``, e.g. a redkitchen run's folder;
without it, 100 random keyframes of 500 ORB features at 320×240), puts it into a DenseSLAM
(``DenseSLAM.from_map``), then times, best of ``--repeat`` (into a fresh folder each time, in the same process):
``slam.save_map(folder)`` (the surfels read from the Taichi fields, every array's CRC-32, map.bin and map.json
written and synced) and ``DenseSLAM.from_map(folder)`` (read, every checksum verified, a new DenseSLAM, the
surfels into its fields), with their parts. Prints one table: measured against the targets (≤ 2 s each, ≤ 120
bytes per surfel plus keyframes).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SAVE_S, LOAD_S, BYTES_PER_SURFEL = 2.0, 2.0, 120  # the targets


def random_surfels(n: int, rng) -> dict[str, np.ndarray]:
    normal = rng.normal(size=(n, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return {"position": rng.uniform(-5, 5, (n, 3)).astype(np.float32), "normal": normal,
            "color": rng.uniform(0, 255, (n, 3)).astype(np.float32), "weight": rng.uniform(0, 30, n).astype(np.float32),
            "radius": rng.uniform(0.001, 0.02, n).astype(np.float32),
            "t_created": rng.integers(0, 2000, n, dtype=np.int32), "t_updated": rng.integers(0, 2000, n, dtype=np.int32),
            "anchor": rng.integers(0, 100, n, dtype=np.int32)}


def random_keyframes(k: int, rng):
    """``k`` keyframes as a run at 640×480 keeps them (ORB at full resolution, depth at 320×240)."""
    import cv2

    from ti_fusion.camera import Intrinsics
    from ti_fusion.loop.keyframes import Keyframe, grid_points
    from ti_fusion.tracking.features import FrameFeatures

    K = Intrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)
    Kd = K.downsampled(2)
    out = []
    for i in range(k):
        n = 500
        kp = tuple(cv2.KeyPoint(float(x), float(y), 31.0, float(a), 1e-4, 0, -1)
                   for x, y, a in zip(rng.uniform(0, 640, n), rng.uniform(0, 480, n), rng.uniform(0, 360, n)))
        pixels = np.array([p.pt for p in kp])
        features = FrameFeatures(kp, rng.integers(0, 256, (n, 32), dtype=np.uint8), pixels, rng.normal(size=(n, 3)))
        depth = rng.uniform(0.5, 4, (240, 320)).astype(np.float32)
        out.append(Keyframe(i, 10 * i, float(i), np.eye(4), features, K, depth, Kd, grid_points(depth, Kd)))
    return K, out


def build(surfels: int, keyframes_from: str | None):
    from ti_fusion.config import Config
    from ti_fusion.slam.saved_map import SavedMap, load_map

    rng = np.random.default_rng(0)
    if keyframes_from:
        saved = load_map(keyframes_from)
        source = f"keyframes of {keyframes_from}"
    else:
        K, kfs = random_keyframes(100, rng)
        saved = SavedMap(K, 1, Config().to_dict(), {}, 0, len(kfs) - 1, 0, kfs)
        source = "100 random keyframes"
    saved.surfels = random_surfels(surfels, rng)
    return saved, source


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.iterdir())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--surfels", type=int, default=1_000_000)
    p.add_argument("--keyframes-from", metavar="RUN_OR_MAP", default=None,
                   help="a run folder or saved map whose keyframes, places and pose graph go with the surfels")
    p.add_argument("--repeat", type=int, default=3)
    args = p.parse_args(argv)
    for name in ("surfels", "repeat"):
        if getattr(args, name) < 1:
            print(f"bench_map_io.py: --{name} {getattr(args, name)}: give at least 1", file=sys.stderr)
            return 2

    from ti_fusion.backend import init_backend
    from ti_fusion.io.map_files import read_map_folder
    from ti_fusion.slam.dense import DenseSLAM
    from ti_fusion.slam.saved_map import SavedMap

    init_backend("cpu")
    saved, source = build(args.surfels, args.keyframes_from)
    slam = DenseSLAM.from_map(saved)
    assert slam.surfels == args.surfels
    times: dict[str, list[float]] = {k: [] for k in ("capture", "save", "read", "parse", "load")}
    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_TMP")) as tmp:
        for r in range(args.repeat + 1):  # the first round compiles the export and import kernels: not counted
            folder = Path(tmp) / f"map{r}"
            t0 = time.perf_counter()
            state = slam.map_state()
            t1 = time.perf_counter()
            slam.save_map(folder)
            t2 = time.perf_counter()
            header, arrays = read_map_folder(folder)
            t3 = time.perf_counter()
            SavedMap.from_arrays(header, arrays)
            t4 = time.perf_counter()
            loaded = DenseSLAM.from_map(folder)
            t5 = time.perf_counter()
            assert loaded.surfels == args.surfels and state.count == args.surfels
            del loaded
            if r:
                for key, dt in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4)):
                    times[key].append(dt)
        table = header["arrays"]
        surfel_bytes = sum(e["bytes"] for name, e in table.items() if name.startswith("surfels/"))
        total = folder_bytes(folder)
    best = {k: min(v) for k, v in times.items()}
    n = args.surfels
    kfs = len(saved.keyframes)
    rest = total - surfel_bytes
    print(f"{n:,} surfels with {source} ({kfs} keyframes); best of {args.repeat}; load average "
          f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    rows = [("save: slam.save_map(folder)", f"{best['save']:.2f} s", f"<= {SAVE_S:g} s",
             best["save"] <= SAVE_S),
            ("  of which map_state() (surfels from the fields)", f"{best['capture']:.2f} s", "", None),
            ("load: DenseSLAM.from_map(folder)", f"{best['load']:.2f} s", f"<= {LOAD_S:g} s", best["load"] <= LOAD_S),
            ("  of which read + checksums (read_map_folder)", f"{best['read']:.2f} s", "", None),
            ("  of which arrays to a SavedMap", f"{best['parse']:.2f} s", "", None),
            ("bytes per surfel (map.bin's surfel arrays / surfels)", f"{surfel_bytes / n:.1f}",
             f"<= {BYTES_PER_SURFEL}", surfel_bytes / n <= BYTES_PER_SURFEL),
            ("keyframes, places, graph, header", f"{rest / 1e6:.1f} MB ({rest / max(kfs, 1) / 1e3:.0f} kB per "
                                                 "keyframe)", "", None),
            ("the folder", f"{total / 1e6:.1f} MB", "", None)]
    width = max(len(r[0]) for r in rows)
    print(f"| {'':{width}} | measured | target | met |")
    for name, value, target, ok in rows:
        print(f"| {name:{width}} | {value} | {target} | {'' if ok is None else 'yes' if ok else 'NO'} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
