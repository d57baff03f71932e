"""``ti-fusion batch``: the manifest checked before any job starts, the line without Ray, and batches on a
local Ray (tiny synthetic jobs): the results table, a failed job, a job killed from outside, resume,
--rerun-failed, and Ctrl-C stopping the jobs with no process left behind.

The batches run as ``python -m ti_fusion batch`` in a process group of their own, so that a signal reaches
them as a terminal's would."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ti_fusion.batch import results
from ti_fusion.batch.manifest import read_manifest
from ti_fusion.batch.runner import MISSING_RAY, Batch, job_env, local_cpus, longest_first, taichi_threads
from ti_fusion.batch.task import error_line
from ti_fusion.cli.main import main
from ti_fusion.errors import TiFusionError
from ti_fusion.io.mcap_log import read_log
from tests.conftest import terminal_signals

TINY = 'downsample = 4\nframes = 3\n'  # 160x120 synthetic frames, three of them


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    return lines[0]


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# --------------------------------------------------------------------------------------------------
# The manifest
# --------------------------------------------------------------------------------------------------
def test_inputs_cross_variants_with_merged_options(tmp_path):
    (tmp_path / "seq").mkdir()
    toml = _write(tmp_path / "m.toml", f"""
[defaults]
{TINY}set = ["icp.iterations=[4, 3, 2]"]

[[inputs]]
scene = "wall"

[[inputs]]
name = "mine"
data = "seq"
depth-scale = 1000
threads = 2

[[variants]]
name = "base"

[[variants]]
name = "depth-only"
set = "icp.color_weight=0"
no_relocalise = true
""")
    m = read_manifest(toml)
    assert [j.name for j in m.jobs] == ["synthetic-wall--base", "synthetic-wall--depth-only", "mine--base",
                                        "mine--depth-only"]
    assert m.inputs == ("synthetic-wall", "mine") and m.variants == ("base", "depth-only")
    wall = m.jobs[1]
    assert sorted(wall.args) == sorted(("--no-relocalise", "--set=icp.iterations=[4, 3, 2]",
                                        "--set=icp.color_weight=0", "--downsample=4", "--frames=3", "--scene=wall"))
    sets = [a for a in wall.args if a.startswith("--set")]
    assert sets == ["--set=icp.iterations=[4, 3, 2]", "--set=icp.color_weight=0"]  # defaults' first, the variant's last
    mine = m.jobs[2]
    assert mine.args[0] == str((tmp_path / "seq").resolve())  # relative to the manifest's folder
    assert "--depth-scale=1000" in mine.args and mine.threads == 2 and m.jobs[0].threads == 1
    yaml = _write(tmp_path / "m.yaml", """
defaults: {downsample: 4, frames: 3, set: ["icp.iterations=[4, 3, 2]"]}
inputs:
  - {scene: wall}
  - {name: mine, data: seq, depth_scale: 1000, threads: 2}
variants:
  - {name: base}
  - {name: depth-only, set: [icp.color_weight=0], no_relocalise: true}
""")
    assert read_manifest(yaml).jobs == m.jobs


BAD_MANIFESTS = [
    ('[[inputs]]\nscene = "room"\nspeed = 3\n', "inputs[0]: unknown key 'speed'"),
    ('[[inputs]]\nscene = "room"\n[extra]\n', "unknown key 'extra' at the top level"),
    ('[defaults]\nframes = 3\n', "no inputs: add at least one [[inputs]] entry"),
    ('[[inputs]]\ndata = "nowhere"\n', "job nowhere: data {dir}/nowhere: no such file or folder"),
    ('[[inputs]]\nscene = "room"\n[[variants]]\nname = "x"\nset = ["icp.nope=1"]\n',
     "variants[0] (x): --set [icp]: unknown setting 'nope'"),
    ('[[inputs]]\nscene = "room"\n[[variants]]\nname = "x"\nset = ["icp.dist_threshold=-1"]\n',
     "variants[0] (x): --set: icp.dist_threshold = -1: must be a number > 0"),
    ('[[inputs]]\nscene = "room"\n[[variants]]\ndata = "x"\n', "variants[0]: unknown key 'data'"),
    ('[[inputs]]\nscene = "room"\nframes = "many"\n', "job synthetic-room: argument --frames: invalid int value"),
    ('[[inputs]]\nscene = "nowhere"\n', "job synthetic-nowhere: argument --scene: invalid choice"),
    ('[[inputs]]\nscene = "room"\nframes = 0\n', "job synthetic-room: --frames 0: must be at least 1"),
    ('[[inputs]]\nscene = "room"\nmesh = "yes"\n', 'inputs[0]: mesh = "yes": expected true or false'),
    ('[[inputs]]\nscene = "room"\nout = "x"\n', "inputs[0]: unknown key 'out'"),
    ('[[inputs]]\nscene = "room"\n[[inputs]]\nscene = "room"\n', "two inputs are named 'synthetic-room'"),
    ('[[inputs]\nscene = "room"\n', "cannot parse the manifest"),
]


@pytest.mark.parametrize("text, expected", BAD_MANIFESTS, ids=[e for _, e in BAD_MANIFESTS])
def test_a_bad_manifest_is_one_line_before_any_job(tmp_path, capsys, monkeypatch, text, expected):
    manifest = _write(tmp_path / "study.toml", text)
    monkeypatch.setattr(Batch, "_on_ray", lambda *a: pytest.fail("a job was started"))
    out = tmp_path / "batch"
    assert main(["batch", str(manifest), "--out", str(out)]) == 2
    line = _one_line(capsys)
    assert line.startswith(f"ti-fusion batch: error: {manifest}: "), line
    assert expected.format(dir=tmp_path.resolve()) in line
    assert not out.exists()  # nothing written, no folder left


def test_without_ray_one_line_names_the_extra(tmp_path, capsys, monkeypatch):
    manifest = _write(tmp_path / "m.toml", f"[defaults]\n{TINY}\n[[inputs]]\nscene = 'room'\n")
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    assert main(["batch", str(manifest), "--out", str(tmp_path / "b")]) == 2
    assert _one_line(capsys) == f"ti-fusion batch: error: {MISSING_RAY}"
    assert "pip install 'ti-fusion[batch]'" in MISSING_RAY


def test_resume_plan_skips_done_keeps_failed_and_reruns_the_rest(tmp_path):
    manifest = _write(tmp_path / "m.toml", "".join(f"[[inputs]]\nname = '{n}'\nscene = 'room'\nframes = 3\n"
                                                   for n in ("done", "failed", "stopped", "changed", "new")))
    m = read_manifest(manifest)
    batch = tmp_path / "b"
    for job, status in zip(m.jobs, ("done", "failed", "interrupted", "done")):
        args = list(job.args) + (["--stride=2"] if job.name == "changed" else [])
        results.write_record(batch, {"job": job.name, "args": args, "status": status})
    run = Batch(m, batch)
    assert [j.name for j in run.plan()] == ["stopped", "changed", "new"]
    assert run.counts == {"ran": 0, "skipped_done": 1, "kept_failed": 1}
    assert [j.name for j in Batch(m, batch, rerun_failed=True).plan()] == ["failed", "stopped", "changed", "new"]
    table = results.rows(batch, m.jobs)
    assert [r["status"] for r in table] == ["done", "failed", "interrupted", "not run", "not run"]


def test_error_line_of_a_job(tmp_path):
    log = tmp_path / "job.log"
    log.write_text("$ python -m ti_fusion slam\nti-fusion slam: warning: something\n"
                   "ti-fusion slam: error: /data: unrecognised dataset layout\n")
    assert error_line(2, log) == "/data: unrecognised dataset layout"
    assert error_line(-signal.SIGKILL, log) == "killed by SIGKILL"
    log.write_text("Traceback (most recent call last):\n  ...\nRuntimeError: boom\n")
    assert error_line(1, log) == "RuntimeError: boom"
    assert error_line(137, log) == "stopped by SIGKILL"


def test_a_local_job_runs_twice_its_threads_in_taichi_up_to_the_cpus(tmp_path):
    # the job left alone at a batch's end uses the CPU its partner left; OpenBLAS, which spins, keeps its share
    assert [taichi_threads(t, cpus) for t, cpus in ((1, 1), (1, 2), (2, 2), (1, 16), (3, 4), (4, 16))] == \
        [1, 2, 2, 2, 4, 8]
    env = job_env(1, 2)
    assert env["TI_CPU_MAX_NUM_THREADS"] == "2" and env["TI_FUSION_PIN_THREADS"] == "0"
    assert env["OMP_NUM_THREADS"] == env["OPENBLAS_NUM_THREADS"] == env["MKL_NUM_THREADS"] == "1"
    assert job_env(3)["TI_CPU_MAX_NUM_THREADS"] == "3"
    job = read_manifest(_write(tmp_path / "m.toml", '[[inputs]]\nscene = "wall"\n')).jobs[0]
    assert Batch(None, tmp_path).taichi_threads(job) == taichi_threads(1, local_cpus())
    assert Batch(None, tmp_path, address="auto").taichi_threads(job) == 1
    assert Batch(None, tmp_path, taichi=3).taichi_threads(job) == 3  # --taichi-threads


def test_jobs_start_longest_first_by_frames_and_pixels(tmp_path):
    inputs = "".join(f'[[inputs]]\nname = "{n}"\nscene = "wall"\n{o}\n' for n, o in (
        ("short", "frames = 10\ndownsample = 2"), ("small", "frames = 20\ndownsample = 4"),
        ("long", "frames = 30"), ("tie", "frames = 10\ndownsample = 2"), ("range", "start = 5\nstop = 25")))
    m = read_manifest(_write(tmp_path / "m.toml", inputs))
    assert [j.name for j in longest_first(m.jobs)] == ["long", "range", "short", "tie", "small"]
    # a job of a whole recording: its length is unknown, and the manifest's order stays
    m = read_manifest(_write(tmp_path / "m.toml", inputs + '[[inputs]]\nname = "all"\nscene = "room"\n'))
    assert [j.name for j in longest_first(m.jobs)] == [j.name for j in m.jobs]


# --------------------------------------------------------------------------------------------------
# Batches on a local Ray
# --------------------------------------------------------------------------------------------------
def _pids_with(text: str) -> list[int]:
    """Processes whose command line holds ``text`` (Linux /proc)."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/cmdline", "rb") as f:
                    if text.encode() in f.read():
                        found.append(int(entry))
            except OSError:
                pass
    return found


def _start_batch(manifest: Path, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "ti_fusion", "batch", str(manifest), "--out", str(out), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=terminal_signals)


def _wait_for_process(text: str, batch: subprocess.Popen) -> int:
    deadline = time.monotonic() + 300  # a bound for a broken batch, not a timing the test depends on
    while time.monotonic() < deadline and batch.poll() is None:
        pids = _pids_with(text)
        if pids:
            return pids[0]
        time.sleep(0.05)
    raise AssertionError(f"no process with {text} started; batch: {batch.communicate()}")


def _stats_so_far(log: Path) -> int:
    """Frames in the log of a run in progress: absent, then empty until its first flush."""
    try:
        return len(read_log(log).stats)
    except (OSError, TiFusionError):
        return 0


def _table(out: Path) -> dict[str, dict]:
    with open(out / "results.csv") as f:
        return {(r["input"], r["variant"]): r for r in csv.DictReader(f)}


pytestmark_ray = pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or not Path("/proc/self").is_dir(),
                                    reason="finds job processes through /proc (Linux)")


@pytest.mark.slow
@pytestmark_ray
def test_batch_table_failed_and_killed_jobs_resume_and_rerun(tmp_path):
    pytest.importorskip("ray")
    (tmp_path / "empty").mkdir()  # no dataset in it: that job fails with its one line
    manifest = _write(tmp_path / "m.toml", f"""[defaults]\n{TINY}
[[inputs]]
scene = "room"
[[inputs]]
name = "victim"
scene = "wall"
[[inputs]]
data = "empty"
""")
    out = tmp_path / "batch"
    proc = _start_batch(manifest, out, "--jobs", "2")
    try:
        victim = _wait_for_process(str(out / "runs" / "victim"), proc)
        with open(f"/proc/{victim}/environ", "rb") as f:
            env = dict(v.split(b"=", 1) for v in f.read().split(b"\0") if b"=" in v)
        os.kill(victim, signal.SIGKILL)
        stdout, stderr = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 1, stderr  # ran to the end; some jobs failed
    rows = _table(out)
    room, killed, empty = rows[("synthetic-room", "")], rows[("victim", "")], rows[("empty", "")]
    summary = json.loads((out / "runs" / "synthetic-room" / "summary.json").read_text())
    assert room["status"] == "done" and room["exit"] == "0" and room["frames"] == "3"
    assert float(room["ate_m"]) == summary["ate_rmse_m"] and room["run_dir"] == "runs/synthetic-room"
    assert killed["status"] == "failed" and killed["exit"] == "-9" and killed["error"] == "killed by SIGKILL"
    assert env[b"TI_CPU_MAX_NUM_THREADS"] == str(taichi_threads(1, local_cpus())).encode()
    assert json.loads((out / "jobs" / "victim.json").read_text())["taichi_threads"] == taichi_threads(1, local_cpus())
    assert empty["status"] == "failed" and empty["exit"] == "2" and "unrecognised dataset layout" in empty["error"]
    assert "| synthetic-room |  | done | 0 | 3 |" in (out / "results.md").read_text()
    assert (out / "ate.png").stat().st_size > 0
    assert "3 jobs: 1 done, 2 failed" in stdout and "victim failed: killed by SIGKILL" in stdout
    # the timeline: Ray's lean start (without its monitor, log monitor and dashboard API), then each job's steps
    timeline = json.loads((out / "summary.json").read_text())["timeline"]
    events = [(event, job) for _, event, job in timeline]
    assert [t for t, _, _ in timeline] == sorted(t for t, _, _ in timeline)
    assert events.index(("ray init", "")) < events.index(("ray node started", "")) < events.index(("ray ready", ""))
    for job in ("synthetic-room", "victim", "empty"):
        steps = [events.index((e, job)) for e in ("task submitted", "task", "job process", "job process end", "result")]
        assert steps == sorted(steps) and events.index(("ray ready", "")) < steps[0]
    assert events.index(("ray shutdown", "")) < events.index(("table and plot written", ""))  # while Ray stops
    assert events.index(("ray shutdown", "")) < events.index(("ray down", ""))

    # resumed: nothing runs (Ray is not even started), the rows stay
    room_record = (out / "jobs" / "synthetic-room.json").read_text()
    again = subprocess.run([sys.executable, "-m", "ti_fusion", "batch", str(manifest), "--out", str(out)],
                           capture_output=True, text=True, timeout=600)
    assert again.returncode == 1, again.stderr
    assert "1 finished jobs skipped, 2 failed kept" in again.stdout and "on Ray" not in again.stdout
    assert _table(out) == rows and (out / "jobs" / "synthetic-room.json").read_text() == room_record

    # --rerun-failed: the victim runs again (and finishes), the empty folder fails again, the finished job stays
    again = subprocess.run([sys.executable, "-m", "ti_fusion", "batch", str(manifest), "--out", str(out),
                            "--rerun-failed"], capture_output=True, text=True, timeout=600)
    assert again.returncode == 1, again.stderr
    rows = _table(out)
    assert rows[("victim", "")]["status"] == "done" and rows[("victim", "")]["frames"] == "3"
    assert rows[("empty", "")]["status"] == "failed"
    assert "2 jobs on Ray" in again.stdout
    assert (out / "jobs" / "synthetic-room.json").read_text() == room_record


@pytest.mark.slow
@pytestmark_ray
def test_ctrl_c_stops_the_running_jobs_and_keeps_the_table(tmp_path):
    pytest.importorskip("ray")
    # a job far longer than the test, stopped once its frame loop has logged frames (a stop during its
    # start-up, e.g. inside a C extension's import, is the run's own business)
    manifest = _write(tmp_path / "m.toml", "[[inputs]]\nscene = 'room'\ndownsample = 4\nframes = 5000\n")
    out = tmp_path / "batch"
    log, run = out / "jobs" / "synthetic-room.log", out / "runs" / "synthetic-room"
    proc = _start_batch(manifest, out)
    try:
        _wait_for_process(str(run), proc)
        deadline = time.monotonic() + 300  # a bound for a broken run, not a timing the test depends on
        while time.monotonic() < deadline and proc.poll() is None and _stats_so_far(run / "log.mcap") < 3:
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the whole foreground group
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, stderr
    assert f"ti-fusion batch: interrupted; what was written is in {out}/" in stderr
    assert _pids_with(str(out)) == []  # no job's process outlives the batch
    row = _table(out)[("synthetic-room", "")]
    assert row["status"] == "interrupted" and row["error"] == "stopped with the batch"
    assert f"ti-fusion slam: stopped by SIGTERM; what was written is in {run}/" in log.read_text()
    assert read_log(run / "log.mcap").complete and (run / "trajectory.tum").is_file()  # the job kept its work


@pytest.mark.slow
@pytestmark_ray
def test_the_lean_local_ray_runs_tasks_at_the_batch_priority():
    ray = pytest.importorskip("ray")
    import logging

    from ti_fusion.batch.runner import start_local_node, stop_local_node

    node = start_local_node(1)
    assert node is not None  # this Ray's internals are the ones the lean start was written for
    try:
        ray.init(address=node.address, log_to_driver=False, logging_level=logging.ERROR)
        # Ray lowers its workers' priority by default (nice 15), and a job's process would inherit it
        job_nice = ray.get(ray.remote(num_cpus=1)(lambda: subprocess.run(
            ["sh", "-c", "nice"], capture_output=True, text=True).stdout.strip()).remote())
        assert job_nice == str(os.nice(0))
        assert ray.cluster_resources().get("CPU") == 1
    finally:
        ray.shutdown()
        stop_local_node(node)
