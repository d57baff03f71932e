"""trajectory.png drawn in a process of its own (ti_fusion/evaluation/plot_process.py): the same file as
drawn in the caller's process, nothing written and False when it cannot draw (the caller then draws and
reports), and no process left whatever the run did with it."""

import os
import signal

import numpy as np
import pytest

from ti_fusion.errors import OutputError
from ti_fusion.evaluation.plot_process import PlotProcess
from ti_fusion.evaluation.plots import plot_trajectory


def _poses(n=40):
    poses = np.stack([np.eye(4)] * n)
    poses[:, 0, 3] = np.linspace(0.0, 1.0, n)
    poses[:, 2, 3] = np.sin(np.linspace(0.0, 3.0, n))
    return poses


def _gone(plotter: PlotProcess) -> bool:
    try:
        os.kill(plotter.pid, 0)
    except ProcessLookupError:
        return True
    with open(f"/proc/{plotter.pid}/stat") as f:  # a zombie is gone too (but for its reaping)
        return f.read().rsplit(")", 1)[1].split()[0] == "Z"


@pytest.mark.slow
def test_the_process_draws_the_file_the_caller_would(tmp_path):
    est = _poses()
    gt = est.copy()
    gt[:, 1, 3] += 0.01
    figure = dict(est_poses=est, gt_poses=gt, timestamps=np.arange(len(est)) * 0.1, title="a run",
                  loop_edges=[(39, 0, True)])
    plotter = PlotProcess.start()
    assert plotter is not None
    assert plotter.plot(path_png=tmp_path / "there.png", **figure)
    plot_trajectory(tmp_path / "here.png", **figure)
    assert (tmp_path / "there.png").read_bytes() == (tmp_path / "here.png").read_bytes()
    assert _gone(plotter)


def test_a_figure_it_cannot_draw_is_left_to_the_caller(tmp_path):
    """A folder where the file should be: False and nothing written; the caller's own draw then says what
    is wrong."""
    plotter = PlotProcess.start()
    path = tmp_path / "trajectory.png"
    path.mkdir()
    assert not plotter.plot(path_png=path, est_poses=_poses())
    assert os.listdir(tmp_path) == ["trajectory.png"] and not os.listdir(path) and _gone(plotter)
    with pytest.raises(OutputError):
        plot_trajectory(path, _poses())


def test_a_process_killed_or_closed_draws_nothing_and_is_reaped(tmp_path):
    plotter = PlotProcess.start()
    os.kill(plotter.pid, signal.SIGKILL)
    assert not plotter.plot(path_png=tmp_path / "t.png", est_poses=_poses())
    assert not (tmp_path / "t.png").exists()
    unused = PlotProcess.start()  # a run that ends without a figure (a stop, no pose)
    unused.close()
    unused.close()
    assert _gone(unused) and _gone(plotter)
    assert not unused.plot(path_png=tmp_path / "t.png", est_poses=_poses())  # closed: nothing drawn there


@pytest.mark.slow
def test_a_run_draws_its_plot_in_the_process_where_matplotlib_is_not_imported(cpu, tmp_path, monkeypatch):
    """A run in a process that has not imported Matplotlib (the command line) starts the plot's process with
    its sinks and has trajectory.png drawn there; none is left when the run ends. (The test session imports
    Matplotlib, so its other runs draw in-process.)"""
    import sys

    from ti_fusion.cli.main import main

    drawn, processes = [], []
    plot = PlotProcess.plot

    def spy(self, **figure):
        processes.append(self)
        drawn.append(plot(self, **figure))
        return drawn[-1]

    monkeypatch.setattr(PlotProcess, "plot", spy)
    monkeypatch.delitem(sys.modules, "matplotlib.figure")
    out = tmp_path / "run"
    assert main(["vo", "--frames", "3", "--downsample", "4", "--out", str(out), "--quiet"]) == 0
    assert drawn == [True] and (out / "trajectory.png").stat().st_size > 0
    assert _gone(processes[0])
