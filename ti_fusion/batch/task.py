"""A batch job's Ray task, on the worker: the job's ``ti-fusion slam`` process, its log, its result.

Its own module, importing only the standard library: a Ray worker imports the module of the function it runs
when it takes its first task, and ``runner`` brings NumPy with the results table, which the task does not
use (docs/BATCH.md, "Ray's start").
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

STOP_GRACE_S = 20.0       # how long a stopped job may take to write what it has before it is killed


def process_started(pid: int | str = "self") -> float | None:
    """When a process started, as ``time.time()`` (Linux /proc; None elsewhere): the batch's timeline."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22, starttime, in clock ticks since boot
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return time.time() - uptime + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def _die_with_parent():  # pragma: no cover - runs in the forked child
    """In the job's process before exec: SIGTERM when the worker that started it dies."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def run_job(spec: dict) -> dict:
    """A Ray task: the job's ``ti-fusion slam`` process, its output into its log file; its exit code, wall
    time, error line and the figures of its run's summary.json. A cancel (the batch stopping) stops the
    process the way Ctrl-C stops a run, and is raised on."""
    entered = time.time()
    argv = [sys.executable, "-m", "ti_fusion", "slam", *spec["args"], "--out", spec["run_dir"], "--overwrite"]
    log_path = Path(spec["log"])
    log_path.parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.update(spec["env"])
    started, at = time.monotonic(), {"worker process": process_started(), "task": entered}
    with open(log_path, "wb") as log:
        log.write(("$ " + " ".join(argv) + "\n").encode())
        log.flush()
        proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, env=env,
                                cwd=spec.get("cwd") if spec.get("cwd") and os.path.isdir(spec["cwd"]) else None,
                                start_new_session=True,  # a terminal's Ctrl-C reaches the batch, which stops the jobs
                                preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
        at["job process"] = time.time()
        try:
            while proc.poll() is None:  # polled: Ray's cancel is raised between Python steps, not in a wait
                time.sleep(0.02)
        except BaseException:
            stop_process(proc)
            raise
    wall = time.monotonic() - started
    at["job process end"] = time.time()
    summary = None
    summary_path = Path(spec["run_dir"]) / "summary.json"
    if proc.returncode == 0:
        try:
            import json

            full = json.loads(summary_path.read_text())
            summary = {k: full.get(k) for k in spec["summary_fields"]}
        except (OSError, ValueError):
            pass
    import socket

    return {"exit_code": proc.returncode, "wall_s": round(wall, 3), "summary": summary, "pid": proc.pid,
            "host": socket.gethostname(), "at": at,
            "error": "" if proc.returncode == 0 and summary is not None else error_line(proc.returncode, log_path)}


def stop_process(proc: subprocess.Popen, grace_s: float = STOP_GRACE_S) -> None:
    """SIGTERM (the run writes what it has), SIGKILL after ``grace_s``."""
    if proc.poll() is not None:
        return
    try:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=grace_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    except BaseException:  # a second stop while waiting: no grace left
        proc.kill()
        proc.wait()
        raise


def error_line(code: int, log_path: Path) -> str:
    """Why a job failed, in one line: the signal that killed it, or the run's own error line."""
    if code < 0:
        return f"killed by {_signal_name(-code)}"
    lines = []
    try:
        with open(log_path, "rb") as f:
            f.seek(max(0, os.fstat(f.fileno()).st_size - 16384))
            lines = [ln.strip() for ln in f.read().decode("utf-8", "replace").splitlines() if ln.strip()]
    except OSError:
        pass
    said = [ln for ln in lines if ln.startswith("ti-fusion slam: ") and "warning:" not in ln]
    if said:
        return said[-1][len("ti-fusion slam: "):].removeprefix("error: ")
    if code == 0:
        return "exited without writing summary.json"
    if code > 128 and code - 128 in signal.valid_signals():
        return f"stopped by {_signal_name(code - 128)}"
    return (lines[-1] if lines else f"exit {code}")[:500]


def _signal_name(n: int) -> str:
    try:
        return signal.Signals(n).name
    except ValueError:
        return f"signal {n}"
