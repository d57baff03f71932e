"""The evaluation against ground truth (ATE and RPE as evo computes them, into summary.json) and
trajectory.png (the estimate against the ground truth, loop edges in the top view)."""

from __future__ import annotations

import sys

import numpy as np

from ti_fusion.evaluation.metrics import held_trajectory, tracked_ate, trajectory_metrics
from ti_fusion.sinks.base import Run, Sink


class EvaluationSink(Sink):
    name = "evaluation"
    commands = ("slam", "vo")  # the commands whose poses are estimates

    def start(self, run: Run) -> None:
        from ti_fusion.evaluation.plot_process import PlotProcess

        # A process imports Matplotlib on the other core while the run starts; where this process has
        # imported it already (a notebook, a test session), drawing here costs no import and the process would.
        self._plotter = None if "matplotlib.figure" in sys.modules else PlotProcess.start()

    def close(self) -> None:
        plotter, self._plotter = getattr(self, "_plotter", None), None
        if plotter is not None:
            plotter.close()

    def finish(self, run: Run) -> dict:
        """ATE/RPE of the posed frames that have ground truth (``gt_frames`` of them; ``gt_note`` says so when
        that is not every posed frame), and trajectory.png."""
        if all(r.pose is None for r in run.results):
            return {}
        # every frame from the first posed one (a rejected or failed frame holds the pose reported for it):
        # no headline from the tracked minority; that one is ate_tracked_only_rmse_m, with the counts
        stamps, poses, gt, tracked = held_trajectory(run.results, run.gt)
        pairs = [(p, g) for p, g in zip(poses, gt) if g is not None]
        tracked = [t for t, g in zip(tracked, gt) if g is not None]
        fields, metrics = {"gt_frames": len(pairs)}, None
        if pairs and 2 * len(pairs) < len(poses):  # a few matches, maybe by chance: no figure to quote as the run's
            fields["gt_note"] = (f"no ATE or RPE: only {len(pairs)} of the {len(poses)} posed frames have ground "
                                 "truth, fewer than half (are its times on the frames' clock?)")
            pairs = []
        if len(pairs) >= 2:
            est, ref = (np.stack(x) for x in zip(*pairs))
            metrics = trajectory_metrics(est, ref)
            fields.update({k: metrics[k] for k in ("ate_rmse_m", "ate_mean_m", "ate_max_m", "rpe_trans_m",
                                                   "rpe_rot_deg", "pairs")})
            path_length = float(np.linalg.norm(np.diff(ref[:, :3, 3], axis=0), axis=1).sum())
            fields["path_length_m"] = round(path_length, 3)
            fields["ate_percent_of_path"] = round(100 * metrics["ate_rmse_m"] / max(path_length, 1e-9), 3)
            fields.update(tracked_ate(est, ref, tracked))
        if pairs and len(pairs) < len(poses):  # some frames lack ground truth: say what the figures are over
            fields["gt_note"] = (f"ATE and RPE are over the {len(pairs)} of {len(poses)} posed frames that have "
                                 "ground truth" if metrics is not None else
                                 f"no ATE or RPE: 1 of the {len(poses)} posed frames has ground truth, they need 2")
        with_gt = len(pairs) == len(poses) and metrics is not None  # else the estimate alone
        title = run.step.plot_title(run) + (f"\n({fields['gt_note']})" if "gt_note" in fields else "")
        edges = run.step.loop_edges()
        path, est, ref = run.out.file("trajectory.png"), np.stack(poses), np.stack(gt) if with_gt else None

        figure = dict(path_png=path, est_poses=est, gt_poses=ref, timestamps=stamps, title=title, metrics=metrics,
                      **({"loop_edges": edges} if edges else {}))
        plotter = getattr(self, "_plotter", None)  # (closed by ``close`` too, should the plot not run)

        def plot():  # in the plot's process, else Matplotlib here, on an outputs' thread beside the map's files
            if plotter is not None and plotter.plot(**figure):
                return
            from ti_fusion.evaluation.plots import plot_trajectory

            plot_trajectory(**figure)

        run.in_background(plot)
        return fields
