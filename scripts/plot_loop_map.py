"""Top-down picture of the loop scene's map without and with loop closure (docs/LOOP_CLOSURE.md).

    .venv/bin/python scripts/loop_consistency.py --scene loop ... --keep RUNS    # RUNS/off, RUNS/on
    .venv/bin/python scripts/plot_loop_map.py RUNS/off RUNS/on --out docs/images/loop_map.png

Each run folder holds the ``surfels.npz`` that ``loop_consistency.py --keep`` writes. Drawn from above
(world x, y; z up), walls only (confirmed surfels whose normal is within 60° of horizontal, between 0.2 m
and 2.4 m high): in blue the surfels created during the first pass, in grey the rest of the map, and in red
the last frames' depth at the run's final poses (what ``loop_consistency.py`` compares with the first
pass). Where the two passes disagree, a wall is drawn twice, blue beside red; where they agree, red lies on
blue. Black lines: the true outside walls and central block. The lower row enlarges the place the last
frames look at.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from ti_fusion.config import FusionConfig  # noqa: E402
from ti_fusion.synthetic.scenes import LOOP_BLOCK, LOOP_CENTER, LOOP_OUTER  # noqa: E402

WALL_NZ = 0.5  # |normal z| below this: a wall (within 60° of horizontal)
Z_BAND = (0.2, 2.4)  # metres: heights drawn (no floor or ceiling)
ZOOM = 3.0  # metres: side of the enlarged square


def load(folder: Path, unstable_weight: float) -> dict:
    d = np.load(folder / "surfels.npz")
    pos, nrm = d["position"], d["normal"]
    wall = (d["weight"] >= unstable_weight) & (np.abs(nrm[:, 2]) < WALL_NZ) & (pos[:, 2] > Z_BAND[0]) \
        & (pos[:, 2] < Z_BAND[1])
    first = wall & (d["t_created"] < int(d["first_pass_frames"]))
    last = d["last_points"]
    last = last[(last[:, 2] > Z_BAND[0]) & (last[:, 2] < Z_BAND[1])]
    return {"first": pos[first, :2], "rest": pos[wall & ~first, :2], "last": last[:, :2]}


def outline(ax) -> None:
    for half in (LOOP_OUTER, LOOP_BLOCK):
        ax.add_patch(Rectangle(LOOP_CENTER - half, 2 * half[0], 2 * half[1], fill=False, lw=0.6, ec="black",
                               zorder=3))


def draw(ax, run: dict, title: str, window=None) -> None:
    size = 0.05 if window is None else 0.4
    rng = np.random.default_rng(0)
    last = run["last"]
    if len(last) > 200_000:
        last = last[rng.choice(len(last), 200_000, replace=False)]
    ax.scatter(*run["rest"].T, s=size, c="0.75", lw=0, rasterized=True)
    ax.scatter(*run["first"].T, s=size, c="tab:blue", lw=0, rasterized=True)
    ax.scatter(*last.T, s=size, c="tab:red", lw=0, alpha=0.5, rasterized=True)
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
                                                              "median of the last frames' points in the on run")
    args = parser.parse_args()
    weight = FusionConfig().unstable_weight
    runs = [load(args.off, weight), load(args.on, weight)]
    cx, cy = args.centre if args.centre else np.median(runs[1]["last"], axis=0)
    window = ((cx - ZOOM / 2, cx + ZOOM / 2), (cy - ZOOM / 2, cy + ZOOM / 2))
    fig, axes = plt.subplots(2, 2, figsize=(12, 9.5), gridspec_kw={"height_ratios": [1, 1.15]})
    for col, (run, label) in enumerate(zip(runs, args.labels)):
        draw(axes[0, col], run, f"{label}: walls from above")
        draw(axes[1, col], run, f"{label}: the {ZOOM:g} m square the last frames see", window)
        (x0, x1), (y0, y1) = window
        axes[0, col].add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=0.8, ec="tab:green",
                                         ls="--", zorder=4))
    axes[0, 0].set_ylabel("y (m)", fontsize=7)
    axes[1, 0].set_ylabel("y (m)", fontsize=7)
    fig.legend(handles=[plt.Line2D([], [], ls="", marker="o", c=c, label=t) for c, t in
                        (("tab:blue", "map: first pass"), ("0.75", "map: the rest"),
                         ("tab:red", "last frames' depth at the final poses"), ("black", "true walls"))],
               loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(args.out)


if __name__ == "__main__":
    main()
