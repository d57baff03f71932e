"""scripts/plot_loop_map.py: which surfels are the first pass, the last pass and the rest, and the picture."""

import sys

import numpy as np


def _run_folder(path, rng):
    """A surfels.npz as loop_consistency.py --keep writes it: 100 fused frames, first pass 30, last 20."""
    n = 600
    position = np.column_stack([rng.uniform(-5, 6, n), rng.uniform(-4, 3, n), rng.uniform(0, 2.6, n)])
    normal = np.tile([1.0, 0.0, 0.0], (n, 1))
    normal[:100] = [0.0, 0.0, 1.0]  # floor and ceiling: not drawn
    created = rng.integers(0, 100, n)
    weight = np.full(n, 10.0)
    weight[100:150] = 1.0  # unconfirmed: not drawn
    path.mkdir()
    np.savez(path / "surfels.npz", position=position.astype(np.float32), normal=normal.astype(np.float32),
             t_created=created.astype(np.int32), weight=weight.astype(np.float32), first_pass_frames=30,
             fused_frames=100, last_pass_frames=20, last_points=position[:10].astype(np.float32))
    drawn = (np.arange(n) >= 150) & (position[:, 2] > 0.2) & (position[:, 2] < 2.4)
    return drawn & (created < 30), drawn & (created >= 80), drawn & (created >= 30) & (created < 80)


def test_passes_and_picture(script, tmp_path, rng, monkeypatch):
    plot = script("plot_loop_map")
    first, last, rest = _run_folder(tmp_path / "off", rng)
    run = plot.load(tmp_path / "off", 3.0)
    assert (len(run["first"]), len(run["last"]), len(run["rest"])) == (first.sum(), last.sum(), rest.sum())
    assert first.sum() > 0 and last.sum() > 0 and rest.sum() > 0  # the case is not vacuous
    _run_folder(tmp_path / "on", rng)
    out = tmp_path / "map.png"
    monkeypatch.setattr(sys, "argv", ["plot_loop_map.py", str(tmp_path / "off"), str(tmp_path / "on"),
                                      "--out", str(out)])
    plot.main()
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
