"""``ti-fusion mesh RUN_DIR|MAP|map.ply``: a coloured triangle mesh of a run's confirmed surfels (docs/MESH.md).

The surfels come from the run folder's map.ply, or from a saved map (a map folder, its map.json, or a run folder
that holds only ``map/``; docs/MAPS.md).

Writes ``mesh.ply`` (binary, vertex colours and normals) and ``mesh.glb`` (glTF binary) into the --out
folder, or, given a run folder and no --out, into that folder beside the run's map. The settings are the config's [mesh] section; --voxel, --min-weight and --max-triangles set the
common ones.
"""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)

HELP = "a coloured triangle mesh (mesh.ply, mesh.glb) of a run's map: RUN_DIR, a saved map or a map.ply"
USES_DATASET = False
USES_TAICHI = True


def add_arguments(parser) -> None:
    parser.add_argument("map", metavar="RUN_DIR|MAP|MAP.ply",
                        help="a run folder of slam or fuse (its map.ply, else its saved map/), a saved map (its "
                             "folder or map.json), or a map.ply itself")
    parser.add_argument("--voxel", type=float, default=None, metavar="METRES",
                        help="edge of the grid's cubes (mesh.voxel_size, default 0.01)")
    parser.add_argument("--min-weight", type=float, default=None, metavar="CONFIDENCE",
                        help="mesh only surfels at least this confident (mesh.min_weight, default 3: confirmed)")
    parser.add_argument("--method", choices=("surfels", "depth"), default="surfels",
                        help="surfels (the map's confirmed surfels; the only one here) or depth (the frames "
                             "re-integrated at the run's poses: made during the run by slam --mesh)")
    parser.add_argument("--max-triangles", type=int, default=None, metavar="N",
                        help="decimate to at most N triangles (mesh.max_triangles; default 0: no decimation)")


def adds_to_run(args) -> str | None:
    """A run folder and no --out: the mesh goes beside the run's map (its summary.json stays the run's)."""
    from ti_fusion.io.outputs import is_run_folder

    return args.map if not getattr(args, "out", None) and is_run_folder(args.map) else None


def map_file(given: str) -> Path:
    """The map that ``given`` (a run folder or a file) names: a map.ply, or a saved map's map.json."""
    from ti_fusion.errors import InputError
    from ti_fusion.io.map_files import HEADER, find_map_folder

    path = Path(given)
    if path.is_dir():
        if (path / "map.ply").is_file():
            return path / "map.ply"
        if (folder := find_map_folder(path)) is not None:
            return folder / HEADER
        raise InputError(path, "holds no map.ply nor a saved map: give the folder of a slam or fuse run, a saved "
                               "map or a map.ply")
    if not path.is_file():
        raise InputError(path, "no such file or folder")
    return path


def saved_surfels(path: Path) -> tuple[dict, object]:
    """(the surfels, the world's up for mesh.glb: the first keyframe's camera -y, or None) of the saved map
    whose map.json is ``path``, every checksum verified."""
    from ti_fusion.io.mesh_files import camera_up
    from ti_fusion.slam.saved_map import load_map

    saved = load_map(path)  # a damaged header is one InputError line there
    surfels = {name: saved.surfels[name] for name in ("position", "normal", "color", "weight", "radius")}
    return surfels, camera_up(saved.keyframes[0].pose) if saved.keyframes else None


def first_camera_up(folder: Path):
    """The world's up for mesh.glb: the first camera's -y in the run's trajectory.tum, or None (the first
    camera's world) when the folder has none."""
    from ti_fusion.io.mesh_files import camera_up
    from ti_fusion.io.trajectory import read_tum

    try:
        _, poses = read_tum(folder / "trajectory.tum")
    except Exception:  # noqa: BLE001 - no or an unreadable trajectory: the map.ply's own world
        return None
    return camera_up(poses[0]) if len(poses) else None


def apply_options(args, mesh_config) -> None:
    """--voxel, --min-weight and --max-triangles into the [mesh] section, checked as --set checks it."""
    from ti_fusion.errors import InputError
    from ti_fusion.mapping.mesh import check_voxel_size

    if getattr(args, "voxel", None) is not None:
        check_voxel_size(args.voxel, "--voxel")
        mesh_config.voxel_size = args.voxel
    if getattr(args, "min_weight", None) is not None:
        if not args.min_weight >= 0:
            raise InputError(None, f"--min-weight {args.min_weight:g}: must be 0 or more")
        mesh_config.min_weight = args.min_weight
    if getattr(args, "max_triangles", None) is not None:
        if args.max_triangles < 0:
            raise InputError(None, f"--max-triangles {args.max_triangles}: must be 0 (no decimation) or more")
        mesh_config.max_triangles = args.max_triangles


def run(ctx) -> dict:
    from ti_fusion.mapping.mesh import mesh_surfels, surfels_from_ply

    from ti_fusion.errors import InputError

    cfg = ctx.config.mesh
    apply_options(ctx.args, cfg)
    if getattr(ctx.args, "method", "surfels") == "depth":
        raise InputError(None, "--method depth re-integrates a run's depth frames, which a run folder does not "
                               "keep: it is made during the run (slam DATA --mesh-method depth)")
    path = map_file(ctx.args.map)
    if ctx.out.adding and not ctx.args.overwrite:
        taken = [n for n in ("mesh.ply", "mesh.glb") if ctx.out.file(n).exists()]
        if taken:
            raise InputError(ctx.out.path, f"holds {' and '.join(taken)} already (slam --mesh's, or an earlier "
                                           "ti-fusion mesh): --overwrite replaces them, --out DIR writes elsewhere")
    from ti_fusion.io.map_files import HEADER

    if path.name == HEADER:
        surfels, up = saved_surfels(path)
    else:
        surfels, up = surfels_from_ply(path), first_camera_up(path.parent)
    stats: dict = {}
    mesh = mesh_surfels(surfels, cfg, source=path, stats=stats)
    from ti_fusion.io.mesh_files import write_run_mesh

    files = write_run_mesh(ctx.out, mesh, up)
    ctx.log(f"{len(mesh)} triangles, {len(mesh.vertices)} vertices, {mesh.area():.2f} m² from "
            f"{stats['surfels_meshed']} of {stats['surfels_in_map']} surfels at {cfg.voxel_size * 100:g} cm voxels "
            f"({stats['ms']['splat'] / 1e3:.2f} s splat, {stats['ms']['extract'] / 1e3:.2f} s marching cubes)")
    if len(mesh) == 0:
        log.warning("the confirmed surfels made no closed cube of the grid: the mesh is empty "
                    "(a larger --voxel bridges sparser surfels)")
    return {"map": str(path), "triangles": len(mesh), "vertices": len(mesh.vertices),
            "area_m2": round(mesh.area(), 4), "voxel_size": cfg.voxel_size, **stats, **files}
