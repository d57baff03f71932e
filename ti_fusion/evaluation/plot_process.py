"""trajectory.png drawn in a process of its own.

    plotter = PlotProcess.start()          # as the run starts: a fresh interpreter imports Matplotlib
    plotter.plot(path_png=..., est_poses=..., ...)   # at its end: True once drawn there, False: draw here
    plotter.close()                        # whatever ended the run: stops and reaps the process

Why: Matplotlib's import and the figure's drawing and layout are about a second of Python (GIL) work at the
run's end, where they slowed the other outputs' Python down as much as they ran beside it (the outputs'
threads share the interpreter with the loop's thread). Started as the run starts, the process imports
Matplotlib on the other core while the loop's thread loads its first kernels, and draws beside the other
outputs at the end (docs/PERFORMANCE.md).

How it starts: as the frame readers, ``io.frame_workers.fresh_interpreter`` (which says why), and takes
the plot's arguments pickled on its stdin and answers one byte on its stdout. It ends when the caller closes
its stdin without arguments, and when the caller is gone (its stdin then ends too). Anything that goes wrong
there (the process gone, a failed draw) makes ``plot`` answer False, and the caller draws the figure itself,
with the errors it raises there.
"""

from __future__ import annotations

import pickle
import subprocess
import sys
import weakref

PLOT_TIMEOUT_S = 300.0  # a figure not drawn by then is drawn by the caller instead


class PlotProcess:
    """A process that has imported ``plot_trajectory`` and draws one figure with it."""

    def __init__(self, proc: subprocess.Popen):
        self._proc = proc
        self._finalizer = weakref.finalize(self, _stop, proc)

    @classmethod
    def start(cls) -> "PlotProcess | None":
        """The process, starting; None where none can start here (the caller then draws in-process)."""
        from ti_fusion.io.frame_workers import fresh_interpreter

        if not sys.executable:
            return None
        try:
            proc = fresh_interpreter(__name__, "_main()", stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL)
        except OSError:
            return None
        return cls(proc)

    @property
    def pid(self) -> int:
        return self._proc.pid

    def plot(self, **kwargs) -> bool:
        """``plot_trajectory(**kwargs)`` in the process; True when it drew and wrote the file, False when it
        did not (gone, failed): then nothing was written, and the caller draws it itself. Once only."""
        try:
            answer, _ = self._proc.communicate(pickle.dumps(kwargs, protocol=pickle.HIGHEST_PROTOCOL),
                                               timeout=PLOT_TIMEOUT_S)
        except (OSError, ValueError, subprocess.TimeoutExpired):  # gone, stuck, or asked twice
            answer = b""
            self._proc.kill()
        self.close()
        return answer == b"1" and self._proc.returncode == 0

    def close(self) -> None:
        """Stop the process (if it has not ended) and reap it."""
        self._finalizer()


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        try:  # no figure to draw: it ends on its own when its stdin ends
            proc.stdin.close()
            proc.wait(timeout=1.0)
        except (OSError, ValueError, subprocess.TimeoutExpired):
            proc.kill()
            proc.wait()
    for pipe in (proc.stdin, proc.stdout):
        if pipe is not None:
            try:
                pipe.close()
            except OSError:
                pass


def _main() -> None:
    """The process: import, wait for the arguments, draw, answer."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the caller decides how the run ends
    from ti_fusion.evaluation.plots import plot_trajectory  # Matplotlib: what this process is for

    data = sys.stdin.buffer.read()
    if not data:  # the run ended without a figure to draw
        return
    plot_trajectory(**pickle.loads(data))  # an error: no answer, and the caller draws (and reports) it
    sys.stdout.buffer.write(b"1")
    sys.stdout.buffer.flush()
