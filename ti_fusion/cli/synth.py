"""``ti-fusion synth OUT_DIR``: the embedded synthetic sequence written to disk in TUM RGB-D format.

Writes to OUT_DIR, which must be new or empty (or hold an earlier run, replaced with --overwrite), a
folder that TUM's tools, evo and Open3D read as a TUM sequence:
    rgb/<timestamp>.png      8-bit RGB
    depth/<timestamp>.png    16-bit, 5000 units per metre, 0 = invalid
    rgb.txt, depth.txt       "timestamp filename" lists with the usual three comment lines
    groundtruth.txt          "timestamp tx ty tz qx qy qz qw", camera-to-world
    associations.txt         "timestamp rgb/... timestamp depth/..." (as associate.py rgb.txt depth.txt)
    intrinsics.txt           "fx fy cx cy" (the TUM loader picks it up from the folder)
    summary.json             frames, size, noise, seed, path length, ms per stage
Timestamps start at 1.0 s and are 1/30 s apart (with --trajectory: the file's own), written with 6 decimals.
--scene picks the scene and its camera path (ti_fusion.synthetic.scenes; docs/DATA.md).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from ti_fusion.errors import InputError
from ti_fusion.geometry import rot_to_quat
from ti_fusion.io.datasets.base import MIN_FRAME_SIZE
from ti_fusion.io.outputs import atomic_write, progress, write_image
from ti_fusion.timing import StageTimer

HELP = "write the synthetic RGB-D sequence to OUT_DIR in TUM format (rgb/, depth/, groundtruth.txt, ...)"
USES_DATASET = False
USES_TAICHI = True
OUT_FROM_POSITIONAL = "out_dir"

DEPTH_SCALE = 5000.0


def add_arguments(parser) -> None:
    parser.add_argument("out_dir", metavar="OUT_DIR",
                        help="folder to write the sequence to: new or empty (or an earlier run's, with --overwrite)")
    from ti_fusion.synthetic.scenes import SCENES

    parser.add_argument("--scene", choices=tuple(SCENES), default=None,
                        help="scene and its camera path (default: synth.scene, room): "
                             + "; ".join(f"{s.name}: {s.about}, {s.frames} frames" for s in SCENES.values()))
    parser.add_argument("--trajectory", default=None, metavar="FILE.tum",
                        help="render these camera-to-world poses (TUM: timestamp tx ty tz qx qy qz qw), one frame "
                             "per pose at its timestamp, instead of the scene's path")
    parser.add_argument("--frames", type=int, default=None,
                        help="number of frames (default: the scene's own length; a trajectory's poses)")
    parser.add_argument("--no-noise", action="store_true", help="ideal depth: no sensor noise, quantisation or drop-outs")
    parser.add_argument("--seed", type=int, default=None, help="noise seed (default: synth.seed, 0)")
    parser.add_argument("--width", type=int, default=None,
                        help="image width; fx scales with it (same field of view); height follows unless given")
    parser.add_argument("--height", type=int, default=None, help="image height")


def synth_config(ctx):
    """The SynthConfig of the config file/--set, with this command's options applied."""
    cfg = ctx.config.synth
    args = ctx.args
    for name, least in (("frames", 1), ("width", MIN_FRAME_SIZE), ("height", MIN_FRAME_SIZE)):
        value = getattr(args, name)
        if value is not None and value < least:
            raise InputError(None, f"--{name} {value}: must be at least {least}")
    if args.frames is not None:
        cfg = replace(cfg, frames=args.frames)
    if args.scene is not None:
        cfg = replace(cfg, scene=args.scene)
    if args.trajectory is not None:
        cfg = replace(cfg, trajectory=args.trajectory)
    if args.no_noise:
        cfg = replace(cfg, noise=False)
    if args.seed is not None:
        cfg = replace(cfg, seed=args.seed)
    if args.width is not None or args.height is not None:
        width = args.width if args.width is not None else round(args.height * cfg.width / cfg.height)
        height = args.height if args.height is not None else round(args.width * cfg.height / cfg.width)
        cfg = replace(cfg, width=width, height=height, fx=cfg.fx * width / cfg.width)
    if cfg.trajectory:
        from ti_fusion.synthetic.scene import read_trajectory

        read_trajectory(cfg.trajectory)  # a bad file: one line before anything is written
    if cfg.frames < 0 or cfg.width < MIN_FRAME_SIZE or cfg.height < MIN_FRAME_SIZE:
        raise InputError(None, f"synth: need at least 1 frame and {MIN_FRAME_SIZE}×{MIN_FRAME_SIZE} pixels (got {cfg.frames} "
                               f"frames, {cfg.width}×{cfg.height})")
    return cfg


def run(ctx) -> dict:
    from ti_fusion.synthetic.scene import SyntheticSequence

    cfg = synth_config(ctx)
    seq = SyntheticSequence(cfg)
    folder = ctx.out.path
    timer = StageTimer()
    write_tum_sequence(seq, folder, timer, show_progress=ctx.config.log.progress)
    path = float(np.linalg.norm(np.diff(seq.poses[:, :3, 3], axis=0), axis=1).sum())
    if not ctx.quiet:
        ctx.log(f"wrote {len(seq)} frames of {cfg.scene} ({cfg.width}×{cfg.height}, noise {'on' if cfg.noise else 'off'}"
                f"{', poses of ' + cfg.trajectory if cfg.trajectory else ''}) to {folder}/")
    return {
        "frames": len(seq),
        "scene": cfg.scene,
        "trajectory": cfg.trajectory,
        "ms_per_stage": timer.summary(skip_first=1),
        "width": cfg.width,
        "height": cfg.height,
        "intrinsics": list(seq.intrinsics.as_tuple()),
        "noise": cfg.noise,
        "seed": cfg.seed,
        "path_length_m": round(path, 4),
        "depth_scale": DEPTH_SCALE,
        "out_dir": str(folder),
    }


def write_tum_sequence(seq, folder: Path, timer: StageTimer | None = None, show_progress: bool = False) -> None:
    """Render every frame of ``seq`` and write the TUM layout described above into ``folder``."""
    timer = timer or StageTimer()
    folder = Path(folder)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    rgb_lines = ["# color images", "# file: 'ti-fusion synthetic'", "# timestamp filename"]
    depth_lines = ["# depth maps", "# file: 'ti-fusion synthetic'", "# timestamp filename"]
    gt_lines = ["# ground truth trajectory", "# file: 'ti-fusion synthetic'", "# timestamp tx ty tz qx qy qz qw"]
    assoc_lines = []
    for i in progress(range(len(seq)), len(seq), "synth", enabled=show_progress):
        with timer.stage("render"):
            depth, color = seq.frame(i)
        stamp = f"{seq.timestamps[i]:.6f}"
        with timer.stage("write"):
            raw = np.round(depth.astype(np.float64) * DEPTH_SCALE)
            raw[(raw > 65535) | ~np.isfinite(raw)] = 0  # beyond the format's 13.1 m: invalid
            write_image(folder / f"rgb/{stamp}.png", color[..., ::-1])
            write_image(folder / f"depth/{stamp}.png", raw.astype(np.uint16))
        T = seq.poses[i]
        q = rot_to_quat(T[:3, :3])
        tx, ty, tz = T[:3, 3]
        rgb_lines.append(f"{stamp} rgb/{stamp}.png")
        depth_lines.append(f"{stamp} depth/{stamp}.png")
        gt_lines.append(f"{stamp} {tx:.9f} {ty:.9f} {tz:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
        assoc_lines.append(f"{stamp} rgb/{stamp}.png {stamp} depth/{stamp}.png")
    K = seq.intrinsics
    files = {
        "rgb.txt": rgb_lines,
        "depth.txt": depth_lines,
        "groundtruth.txt": gt_lines,
        "associations.txt": assoc_lines,
        "intrinsics.txt": [f"{K.fx:.6f} {K.fy:.6f} {K.cx:.6f} {K.cy:.6f}"],
    }
    for name, lines in files.items():
        with atomic_write(folder / name, "w") as f:
            f.write("\n".join(lines) + "\n")
