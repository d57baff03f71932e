"""Top-down picture of the loop scene's map without and with loop closure (docs/LOOP_CLOSURE.md).

    .venv/bin/python scripts/loop_consistency.py --scene loop ... --keep RUNS    # RUNS/off, RUNS/on
    .venv/bin/python scripts/plot_loop_map.py RUNS/off RUNS/on --out docs/images/loop_map.png

Each run folder holds the ``surfels.npz`` that ``loop_consistency.py --keep`` writes. Drawn from above
(world x, y; z up), walls only (confirmed surfels whose normal is within 60° of horizontal, between 0.2 m
and 2.4 m high): in blue the surfels created during the first pass, in red those created during the last
frames, in grey the rest of the map. Where the last pass comes back with drift, it does not find the first
pass's walls within fusion's gates and lays down its own beside them: a wall drawn twice, blue and red. Where
the poses agree, the last frames merge into the first pass's surfels and few red ones are created. Black
lines: the true outside walls and central block. The lower row enlarges a square where the two passes meet.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from ti_fusion.config import FusionConfig  # noqa: E402
from ti_fusion.synthetic.scenes import LOOP_BLOCK, LOOP_CENTER, LOOP_OUTER  # noqa: E402

WALL_NZ = 0.5  # |normal z| below this: a wall (within 60° of horizontal)
Z_BAND = (0.2, 2.4)  # metres: heights drawn (no floor or ceiling)
ZOOM = 2.5  # metres: side of the enlarged square


def load(folder: Path, unstable_weight: float) -> dict:
    d = np.load(folder / "surfels.npz")
    pos, nrm, created = d["position"], d["normal"], d["t_created"]
    wall = (d["weight"] >= unstable_weight) & (np.abs(nrm[:, 2]) < WALL_NZ) & (pos[:, 2] > Z_BAND[0]) \
        & (pos[:, 2] < Z_BAND[1])
    first = wall & (created < int(d["first_pass_frames"]))
    last = wall & (created >= int(d["fused_frames"]) - int(d["last_pass_frames"]))
    return {"first": pos[first, :2], "rest": pos[wall & ~first & ~last, :2], "last": pos[last, :2]}


def outline(ax) -> None:
    for half in (LOOP_OUTER, LOOP_BLOCK):
        ax.add_patch(Rectangle(LOOP_CENTER - half, 2 * half[0], 2 * half[1], fill=False, lw=0.6, ec="black",
                               zorder=3))


def draw(ax, run: dict, title: str, window=None) -> None:
    size = 0.05 if window is None else 0.4
    ax.scatter(*run["rest"].T, s=size, c="0.75", lw=0, rasterized=True)
    ax.scatter(*run["first"].T, s=size, c="tab:blue", lw=0, rasterized=True)
    ax.scatter(*run["last"].T, s=size, c="tab:red", lw=0, rasterized=True)
    outline(ax)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9)
    ax.tick_params(labelsize=7)
    if window is not None:
        (x0, x1), (y0, y1) = window
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
    else:
        pad = 0.3
        ax.set_xlim(LOOP_CENTER[0] - LOOP_OUTER[0] - pad, LOOP_CENTER[0] + LOOP_OUTER[0] + pad)
        ax.set_ylim(LOOP_CENTER[1] - LOOP_OUTER[1] - pad, LOOP_CENTER[1] + LOOP_OUTER[1] + pad)
    ax.set_xlabel("x (m)", fontsize=7)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("off", type=Path, help="run folder without loop closure (with surfels.npz)")
    parser.add_argument("on", type=Path, help="run folder with loop closure")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    parser.add_argument("--labels", nargs=2, default=("loop closure off", "loop closure on"))
    parser.add_argument("--centre", type=float, nargs=2, help="x y (m) of the enlarged square; default: the "
                                                              "median of the off run's last-pass wall surfels "
                                                              "within 0.5 m of a first-pass one")
    args = parser.parse_args()
    weight = FusionConfig().unstable_weight
    runs = [load(args.off, weight), load(args.on, weight)]
    if args.centre:
        cx, cy = args.centre
    else:
        off = runs[0]
        meet = cKDTree(off["first"]).query(off["last"], distance_upper_bound=0.5)[0] < 0.5
        cx, cy = np.median(off["last"][meet], axis=0) if meet.any() else LOOP_CENTER
    window = ((cx - ZOOM / 2, cx + ZOOM / 2), (cy - ZOOM / 2, cy + ZOOM / 2))
    fig, axes = plt.subplots(2, 2, figsize=(12, 9.5), gridspec_kw={"height_ratios": [1, 1.15]})
    for col, (run, label) in enumerate(zip(runs, args.labels)):
        draw(axes[0, col], run, f"{label}: walls from above")
        draw(axes[1, col], run, f"{label}: a {ZOOM:g} m square where the passes meet", window)
        (x0, x1), (y0, y1) = window
        axes[0, col].add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=0.8, ec="tab:green",
                                         ls="--", zorder=4))
    axes[0, 0].set_ylabel("y (m)", fontsize=7)
    axes[1, 0].set_ylabel("y (m)", fontsize=7)
    fig.legend(handles=[plt.Line2D([], [], ls="", marker="o", c=c, label=t) for c, t in
                        (("tab:blue", "surfels created in the first pass"),
                         ("tab:red", "surfels created in the last frames"), ("0.75", "the rest of the map"),
                         ("black", "true walls"))],
               loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(args.out)


if __name__ == "__main__":
    main()
