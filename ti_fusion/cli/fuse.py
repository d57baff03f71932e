"""``ti-fusion fuse DATA``: point-based fusion of a sequence with its ground-truth poses.

The classic assignment's fusion experiment: integrate every frame at its ground-truth pose, then report
the surfel count against the naive count (every valid input point concatenated) and their ratio.
Writes ``map.ply`` (positions, normals, colours), ``map_color.png`` and ``map_normals.png`` (the map
from the first camera pulled back ``fusion.view_back`` metres, coloured by colour and by normal).
"""

from __future__ import annotations

import time

from ti_fusion.io.datasets import open_dataset
from ti_fusion.errors import InputError
from ti_fusion.mapping.mapper import STAGES, SurfelMapper
from ti_fusion.kernels.maps import FrameMaps
from ti_fusion.io.outputs import progress
from ti_fusion.mapping.views import save_views, view_pose
from ti_fusion.slam.timing import StageTimer

HELP = "fuse frames at their ground-truth poses into a surfel map: counts, compression, map.ply, PNG views"
USES_DATASET = True
USES_TAICHI = True


def add_arguments(parser) -> None:
    parser.add_argument("--no-views", action="store_true", help="skip the PNG views of the map")


def run(ctx) -> dict:
    cfg = ctx.config
    dataset = open_dataset(cfg.dataset, cfg.synth)
    if not dataset.has_ground_truth:
        raise InputError(dataset.root, "this sequence has no ground-truth poses, which fuse needs "
                                       "(ti-fusion slam estimates poses instead)")
    if len(dataset) == 0:
        raise InputError(dataset.root, "no frames selected (check --start/--stop/--frames)")
    K = dataset.intrinsics
    # The frame maps the SLAM loop fuses from: averaged down to the map's level on input (by default)
    input_level = cfg.frame_input_level(K.width)
    maps = FrameMaps(cfg.maps, K.height, K.width, levels=cfg.fusion.map_level(K.width) - input_level + 1,
                     input_level=input_level)
    mapper = SurfelMapper(cfg.fusion)
    timer = StageTimer()
    naive = merged = added = removed = covered = 0
    first_pose = None
    t0 = time.perf_counter()
    for i, frame in enumerate(progress(dataset, len(dataset), "fuse", cfg.log.progress and not ctx.quiet)):
        if frame.gt_pose is None:
            raise InputError(dataset.root, f"frame {frame.index} has no ground-truth pose")
        if first_pose is None:
            first_pose = frame.gt_pose
        with timer.stage("maps"):
            # The same maps the SLAM loop fuses: edge-preserving smoothed depth, normals from it.
            maps.compute(frame.depth, frame.intrinsics)
        stats = mapper.integrate(maps, frame.color, frame.gt_pose, i, timer)
        timer.add("fuse", sum(stats.ms.values()))
        naive += int((frame.depth > 0).sum())
        merged, added, removed = merged + stats.merged, added + stats.added, removed + stats.removed
        covered += stats.covered
    wall = time.perf_counter() - t0
    frames = len(dataset)

    with timer.stage("export"):
        ply = mapper.export_ply(ctx.out.file("map.ply"))
        views = {} if ctx.args.no_views else save_views(mapper.map, view_pose(first_pose, cfg.fusion.view_back),
                                                       ctx.out.path)
    surfels = mapper.count
    all_pixels = frames * K.width * K.height
    ratio = surfels / naive if naive else None
    ms = timer.summary(skip_first=1)  # the first frame pays the kernels' compilation
    print(f"surfels: {surfels:,}  naive points (valid depth, {frames} frames): {naive:,}  "
          f"compression ratio: {100 * ratio:.2f}%" if ratio is not None else f"surfels: {surfels:,} (no valid depth)",
          flush=True)
    print(f"  (every pixel, as the classic report counts: {all_pixels:,} → {100 * surfels / all_pixels:.2f}%)",
          flush=True)
    print("  ms per frame (median): " + ", ".join(f"{s} {ms[s]['median']:.2f}" for s in ("maps", *STAGES, "fuse")
                                                 if s in ms), flush=True)
    return {
        "frames": frames,
        "wall_s": wall,
        "ms_per_stage": ms,
        "dataset": dataset.describe(),
        "surfels": surfels,
        "naive_points": naive,
        "compression_ratio": ratio,
        "all_pixels": all_pixels,
        "compression_ratio_all_pixels": surfels / all_pixels,
        "merged": merged,
        "added": added,
        "removed": removed,
        "covered": covered,
        "capacity": mapper.map.capacity,
        "ply": str(ply),
        "views": {k: str(v) for k, v in views.items()},
    }
