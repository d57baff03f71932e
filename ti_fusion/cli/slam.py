"""``ti-fusion slam DATA``: frame-to-model dense SLAM over a sequence (the pipeline with ``SLAMStep``); the
switches of the optional outputs come from their sinks (``ti_fusion.sinks``)."""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

HELP = "dense SLAM (frame-to-model ICP + surfel fusion): trajectory, map, MCAP log, plots, ATE/RPE"
USES_DATASET = True
USES_TAICHI = True


def add_arguments(parser) -> None:
    from ti_fusion.sinks import add_switches

    parser.add_argument("--no-relocalise", action="store_true",
                        help="after a tracking failure, do not re-initialise with ORB + PnP features")
    parser.add_argument("--mesh", action="store_true",
                        help="also a coloured triangle mesh of the map: mesh.ply, mesh.glb and /map/mesh in the log "
                             "(settings: the [mesh] config section; docs/MESH.md)")
    parser.add_argument("--mesh-method", choices=("depth", "surfels"), default=None,
                        help="--mesh from: depth = the frames re-integrated at their poses (mesh.method, default), "
                             "surfels = the map's confirmed surfels; implies --mesh")
    parser.add_argument("--live", metavar="[HOST:]PORT", default=None,
                        help="serve the run to Foxglove while it runs (Open connection > Foxglove WebSocket, "
                             "ws://HOST:PORT); HOST defaults to 127.0.0.1, PORT 0 picks a free port")
    add_switches(parser, "slam")  # the optional outputs' own switches, e.g. --splats


def run(ctx) -> dict:
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.sinks import chosen
    from ti_fusion.slam.pipeline import SLAMPipeline

    cfg = ctx.config
    if ctx.args.no_relocalise:
        cfg.slam.relocalise = "none"
    if ctx.args.mesh or ctx.args.mesh_method:
        cfg.mesh.after_run = True
    if ctx.args.mesh_method:
        cfg.mesh.method = ctx.args.mesh_method
    if cfg.map.localize and not cfg.map.map:
        from ti_fusion.errors import InputError

        raise InputError(None, "--localize tracks against a saved map: give it with --map RUN_OR_MAP_DIR")
    outputs = chosen(ctx.args, "slam")
    if outputs.get("saved_map") is False and cfg.map.save_map:
        from ti_fusion.errors import InputError

        raise InputError(None, f"--no-save-map writes no saved map and --save-map {cfg.map.save_map} names where "
                               "it goes: give one of them")
    dataset = open_dataset(cfg.dataset, cfg.synth)
    if not ctx.quiet:  # what the format line (format, depth scale, intrinsics) does not say
        d = dataset.describe()
        name = d["name"]
        if d["format"] == "synthetic":
            name = "the synthetic sequence" + ("" if d["scene"] == "room" else f" (scene {d['scene']})") + \
                (f" along {d['trajectory']}" if d.get("trajectory") else "")
        frames = "frames until Ctrl-C" if d["frames"] is None else f"{d['frames']} frames"  # None: a live camera
        ctx.log(f"{name}: {frames} at {d['width']}x{d['height']}")
    live = _live_server(ctx)
    try:
        summary = SLAMPipeline(dataset, cfg, ctx.out, ctx.backend, show_progress=not ctx.quiet, live=live,
                               outputs=outputs).run()
    finally:  # the log closes the server; this covers a run that stops before its log is open
        if live is not None:
            live.close()
    _print_summary(ctx, summary)
    return summary


def _live_server(ctx):
    if ctx.args.live is None:
        return None
    from ti_fusion.io.live import LiveServer

    live = LiveServer(ctx.args.live)
    urls = live.urls()
    if live.every_interface:
        import logging

        logging.getLogger("ti_fusion").warning(
            f"live: serving on every network interface ({live.host or '*'}): anyone who can reach this machine on "
            f"port {live.port} can watch the run (--live 127.0.0.1:{live.port} keeps it to this machine)")
        where = "; from another machine: " + ", ".join(urls[1:]) if len(urls) > 1 else \
            "; from another machine: ws://<this machine's address>:" + str(live.port)
    else:
        where = ""
    # even with --quiet: the line says where to connect
    ctx.log(f"live: {urls[0]} (in Foxglove: Open connection > Foxglove WebSocket){where}")
    return live


def _print_summary(ctx, s: dict) -> None:
    fps = f"{s['fps_processing']} fps processing (after warm-up)" if s["fps_processing"] is not None else \
        "no fps processing (every frame was warm-up)"
    line = f"{s['frames']} frames, {s['surfels']} surfels, {fps}, {s['fps_wall']} fps wall-clock (the whole loop"
    line += f"; {s['process_s']:.1f} s since the process started)" if s.get("process_s") is not None else ")"
    if "ate_rmse_m" in s:
        line += (f", ATE {s['ate_rmse_m'] * 100:.2f} cm ({s['ate_percent_of_path']:.2f}% of "
                 f"{s['path_length_m']:.2f} m) over all {s['ate_frames']} frames{_tracked_only(s, 100, 'cm')}, "
                 f"RPE {s['rpe_trans_m'] * 1000:.1f} mm")
    line += f", tracking failures: {s['tracking_failures']}"
    ctx.log(line)
    if "session" in s:  # a session against a saved map (--map)
        found = s["found"]
        where = (f"found itself in the map at frame {found['frame']} (its keyframe {found['keyframe']}), after "
                 f"{found['unlocalised_before']} frame(s) not localised") if found else \
            f"did not find itself in the map; its own map from frame {s['own_map_at']}"
        ctx.log(f"session ({'--localize: the map unchanged' if s['session'] == 'localize' else 'extending the map'}): "
                f"{where}; {s['unlocalised_frames']} frame(s) without a pose" + (
                    f", {s['odometry_frames']} posed by odometry off the map (not localised against it)"
                    if s.get("odometry_frames") else ""))
    if s.get("gt_note"):
        log.warning(s["gt_note"])
    hint = _small_frames_hint(ctx.config, s)
    if hint:
        log.warning(hint)


def _small_frames_hint(cfg, s: dict) -> str | None:
    """Where most frames were lost for too few ICP inliers and the frames are small for ICP's pyramid: the
    icp.iterations with fewer levels that leaves the coarsest level pixels enough (None otherwise)."""
    from ti_fusion.slam.dense import COARSE_PIXELS_PER_INLIER

    lost = [f for f in s.get("failed_frames", []) if "too few inliers" in f["reason"]]
    if not lost or 2 * len(lost) < s["frames"] - 1 or "resolution" not in s:  # most tracked frames lost that way
        return None
    width, height = s["resolution"]["tracked_at"]
    iterations, needed = list(cfg.icp.iterations), COARSE_PIXELS_PER_INLIER * cfg.icp.min_inliers
    levels = len(iterations)
    while levels > 1 and (width >> (levels - 1)) * (height >> (levels - 1)) < needed:
        levels -= 1
    if levels == len(iterations):
        return None
    keep = iterations[:levels]
    return (f"{s['tracking_failures']} of {s['frames']} frames were lost with too few ICP inliers: frames tracked at "
            f"{width}x{height} are small for ICP's {len(iterations)} pyramid levels (its coarsest "
            f"{width >> (len(iterations) - 1)}x{height >> (len(iterations) - 1)}); --set icp.iterations="
            f"[{','.join(map(str, keep))}] keeps {levels} (coarsest {width >> (levels - 1)}x{height >> (levels - 1)})")


def _tracked_only(s: dict, scale: float, unit: str) -> str:
    """The ATE over the tracked frames alone, labelled, where some frames were not tracked (else nothing)."""
    if not s.get("untracked_frames"):
        return ""
    value = s.get("ate_tracked_only_rmse_m")
    shown = "n/a" if value is None else f"{value * scale:.2f} {unit}"
    return f" (lost or rejected frames hold the last pose; over the {s['tracked_frames']} tracked alone: {shown})"
