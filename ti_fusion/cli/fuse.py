"""``ti-fusion fuse DATA``: point-based fusion of a sequence with its ground-truth poses (the pipeline with
``FuseStep``): surfel count against the naive point count, map.ply and PNG views of the map."""

from __future__ import annotations

from ti_fusion.io.datasets import open_dataset
from ti_fusion.mapping.mapper import STAGES
from ti_fusion.sinks import add_switches, chosen
from ti_fusion.slam.fuse_step import FuseStep
from ti_fusion.slam.pipeline import Pipeline

HELP = "fuse frames at their ground-truth poses into a surfel map: counts, compression, map.ply, PNG views"
USES_DATASET = True
USES_TAICHI = True


def add_arguments(parser) -> None:
    parser.add_argument("--no-views", action="store_true", help="skip the PNG views of the map")
    add_switches(parser, "fuse")  # the optional outputs' own switches (ti_fusion.sinks)


def run(ctx) -> dict:
    cfg = ctx.config
    dataset = open_dataset(cfg.dataset, cfg.synth)
    outputs = {**chosen(ctx.args, "fuse"), **({"views": False} if ctx.args.no_views else {})}
    summary = Pipeline(dataset, cfg, ctx.out, FuseStep(cfg, dataset), ctx.backend, show_progress=not ctx.quiet,
                       outputs=outputs).run()
    _print_summary(summary)
    return summary


def _print_summary(s: dict) -> None:
    surfels, naive, ratio = s["surfels"], s["naive_points"], s["compression_ratio"]
    print(f"surfels: {surfels:,}  naive points (valid depth, {s['frames']} frames): {naive:,}  "
          f"compression ratio: {100 * ratio:.2f}%" if ratio is not None else f"surfels: {surfels:,} (no valid depth)",
          flush=True)
    print(f"  (every pixel, as the classic report counts: {s['all_pixels']:,} → "
          f"{100 * s['compression_ratio_all_pixels']:.2f}%)", flush=True)
    ms = s["ms_per_stage"]
    print("  ms per frame (median): " + ", ".join(f"{k} {ms[k]['median']:.2f}" for k in ("pyramid", *STAGES, "fuse")
                                                 if k in ms), flush=True)
