"""The batch's jobs on Ray: each a ``ti-fusion slam`` process started by a Ray task that asks for the CPUs
(Taichi's threads) and GPUs the job uses.

- Local by default: a Ray instance of this process's own (``address="local"``, never another's that happens
  to run here) with as many CPUs as this process may use, so ``cores // threads`` jobs run at once. Each job's
  Taichi runs ``threads`` CPU threads (``TI_CPU_MAX_NUM_THREADS``, which Taichi reads at ``ti.init``), its
  BLAS/OpenMP pools as many, and its workers are not pinned (``TI_FUSION_PIN_THREADS=0``: every job would
  pin its workers to the same first CPUs).
- ``address``: an existing cluster (``auto``, ``HOST:PORT``, ``ray://HOST:10001``); its nodes need ti-fusion
  installed and the batch folder and the inputs at the same paths (a shared file system).
- A job's process that fails or is killed is a failed row; the batch goes on. Ctrl-C (or SIGTERM) cancels
  the running tasks: each sends its job SIGTERM (the run keeps its trajectory and log, as it does for a
  user's Ctrl-C), kills it after ``STOP_GRACE_S``, and the batch keeps every finished row. A job's process
  also gets SIGTERM from the kernel if the Ray worker that started it dies (``PR_SET_PDEATHSIG``, Linux),
  so no job outlives its batch.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
from datetime import datetime
from pathlib import Path

from ti_fusion.batch import results
from ti_fusion.batch.manifest import Job
from ti_fusion.batch.task import STOP_GRACE_S, process_started, run_job
from ti_fusion.errors import InputError, TiFusionError

log = logging.getLogger(__name__)

# Ray lowers its workers' priority (nice 15) and a job's process inherits it: a batch's job then yields
# to everything else on the machine, a run alone does not. Workers keep the batch's own priority.
RAY_SYSTEM_CONFIG = {"worker_niceness": 0}
MISSING_RAY = "ti-fusion batch runs its jobs on Ray, which is not installed: pip install 'ti-fusion[batch]'"


def import_ray():
    """Ray, or one line naming the extra that installs it."""
    try:
        import ray
    except ImportError:
        raise TiFusionError(MISSING_RAY) from None
    return ray


def local_cpus() -> int:
    """The CPUs this process may use (its affinity, which containers and taskset narrow)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def start_local_node(cpus: int):
    """A Ray head on this machine with only what the batch's tasks need: its GCS, raylet (with the raylet's
    agents) and workers, without the autoscaler's monitor, the log monitor (the batch does not forward the
    workers' output) and the dashboard's API server: three Python processes that each import Ray, half of
    ``ray.init``'s CPU time (docs/BATCH.md, "Ray's start"). Ray's own ``Node``, which ``ray.init`` starts,
    with those three turned off; None where this Ray's internals differ, and ``ray.init`` then starts the
    usual node."""
    try:
        from ray._private.node import Node
        from ray._private.parameter import RayParams
    except ImportError:
        return None

    class BatchNode(Node):
        def start_api_server(self, *args, **kwargs):  # the dashboard's API: the batch asks it nothing
            return None

    try:
        try:  # as ray.init does for the clusters it starts
            from ray._common.usage.usage_lib import set_usage_stats_enabled_via_env_var

            set_usage_stats_enabled_via_env_var(False)
        except ImportError:
            os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        params = RayParams(num_cpus=cpus, include_dashboard=False, no_monitor=True, include_log_monitor=False,
                           _system_config=RAY_SYSTEM_CONFIG)
        return BatchNode(params, head=True, shutdown_at_exit=False, spawn_reaper=True, ray_init_cluster=True)
    except Exception as exc:  # another Ray's internals: the usual start
        log.debug("Ray's lean start failed (%s); ray.init starts the usual node", exc)
        return None


def stop_local_node(node) -> None:
    """What ``ray.shutdown`` does for the node ``ray.init`` started: its processes, raylet first."""
    try:
        node.kill_all_processes(check_alive=False, allow_graceful=True)
    except Exception as exc:
        log.debug("stopping Ray's node: %s", exc)


def _import_plotting() -> None:
    """Matplotlib for ate.png, imported while Ray starts (the driver only waits then) rather than after the
    last job, where it adds to the batch's time."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot  # noqa: F401
    except Exception:  # plot_ate says what is wrong, where it is drawn
        pass


def taichi_threads(threads: int, cpus: int) -> int:
    """Taichi's CPU threads in a local job that asks Ray for ``threads`` CPUs on a machine of ``cpus``: twice
    as many, at most ``cpus``, so that the job left running alone at the batch's end also uses the CPUs
    its finished partners left idle (docs/BATCH.md, "Threads and Ray")."""
    return max(threads, min(cpus, 2 * threads))


def job_env(threads: int, taichi: int | None = None) -> dict[str, str]:
    """What a job's process gets on top of the worker's environment: the driver's Taichi and ti-fusion
    settings (a cluster's workers do not inherit the driver's environment), and its thread counts: Taichi's
    ``taichi`` (default ``threads``), OpenMP's and BLAS's ``threads`` (OpenBLAS spins while it waits, and
    would take a partner job's CPU)."""
    env = {k: v for k, v in os.environ.items() if k.startswith(("TI_", "TI_FUSION_"))}
    env.update({"TI_CPU_MAX_NUM_THREADS": str(taichi or threads), "TI_FUSION_PIN_THREADS": "0",
                "OMP_NUM_THREADS": str(threads), "OPENBLAS_NUM_THREADS": str(threads),
                "MKL_NUM_THREADS": str(threads)})
    return env


def job_size(job: Job) -> float | None:
    """A job's work, to start the longest first: its frames times its share of the full image's pixels
    (frames / downsample²); None where its arguments do not say how many frames (a whole recording)."""
    opts = dict(a[2:].split("=", 1) for a in job.args if a.startswith("--") and "=" in a)
    try:
        if "frames" in opts:
            frames = float(opts["frames"])
        elif "stop" in opts:
            frames = (int(opts["stop"]) - int(opts.get("start", 0))) / int(opts.get("stride", 1))
        else:
            return None
        return frames / int(opts.get("downsample", 1)) ** 2
    except (ValueError, ZeroDivisionError):
        return None


def longest_first(jobs: list[Job]) -> list[Job]:
    """The jobs by ``job_size``, largest first (ties in the manifest's order), so that the batch does not
    end on a long job with the other slots idle; the manifest's order where any job's size is unknown."""
    sizes = {j.name: job_size(j) for j in jobs}
    if any(size is None for size in sizes.values()):
        return list(jobs)
    return sorted(jobs, key=lambda j: -sizes[j.name])


# -- on the driver ---------------------------------------------------------------------------------------------
class Batch:
    """One invocation over one manifest and one batch folder."""

    def __init__(self, manifest, folder: Path, *, address: str | None = None, max_jobs: int | None = None,
                 rerun_failed: bool = False, progress: bool = True, say=print, taichi: int | None = None):
        self.manifest, self.folder = manifest, Path(folder)
        self.taichi = taichi  # every job's Taichi threads, where given (--taichi-threads)
        self.address, self.max_jobs, self.rerun_failed = address, max_jobs, rerun_failed
        self.progress, self.say = progress, say
        self.counts = {"ran": 0, "skipped_done": 0, "kept_failed": 0}
        self.ray_start_s: float | None = None  # how long Ray took to start or connect (None: not needed)
        # (time.time(), event, job): where a batch's time goes, in its summary.json and bench_batch.py's output
        self.origin = process_started() or time.time()
        self.events: list[tuple[float, str, str]] = []
        self._table: list[dict] | None = None  # the rows, once written
        self._writer: threading.Thread | None = None  # writes them while Ray stops

    def mark(self, event: str, job: str = "", at: float | None = None) -> None:
        self.events.append((time.time() if at is None else at, event, job))

    def timeline(self) -> list[list]:
        """[seconds since this process started, event, job], in time order."""
        return [[round(t - self.origin, 3), event, job] for t, event, job in sorted(self.events)]

    # what to do with each job
    def plan(self) -> list[Job]:
        to_run = []
        for job in self.manifest.jobs:
            rec = results.read_record(self.folder, job.name)
            if rec is not None and tuple(rec.get("args", ())) == job.args:
                if rec.get("status") == results.DONE:
                    self.counts["skipped_done"] += 1
                    continue
                if rec.get("status") == results.FAILED and not self.rerun_failed:
                    self.counts["kept_failed"] += 1
                    continue
            to_run.append(job)
        return to_run

    def run(self) -> list[dict]:
        """Run what the plan says, then write the table and plot from every job's record; the table too when
        the batch is stopped, with the finished rows."""
        self.mark("batch start")
        to_run = self.plan()
        if self.counts["skipped_done"] or self.counts["kept_failed"]:
            kept = self.counts["kept_failed"]
            self.say(f"resuming {self.folder}: {self.counts['skipped_done']} finished jobs skipped" +
                     (f", {kept} failed kept (--rerun-failed runs them again)" if kept else ""))
        if to_run and self.address is None:
            cpus = local_cpus()
            too_big = [j for j in to_run if j.threads > cpus]
            if too_big:
                raise InputError(self.manifest.path, f"job {too_big[0].name}: threads {too_big[0].threads} is "
                                                     f"more than the {cpus} CPUs here")
        try:
            if to_run:
                self._on_ray(to_run)
        finally:
            if self._writer is not None:  # a second Ctrl-C during its join: it still writes, not beside us
                self._writer.join()
            if self._table is None:  # no Ray, or its writer did not get to end
                self._write_results()
        return self._table

    def _write_results(self) -> None:
        """The table and the plot from every job's record."""
        table = results.rows(self.folder, self.manifest.jobs)
        results.write_tables(self.folder, table)
        try:
            results.plot_ate(self.folder, table, self.manifest.inputs, self.manifest.variants)
        except Exception as exc:  # the table is the result; a plot that fails says so and is left out
            log.warning("no ate.png: %s", exc)
        self.mark("table and plot written")
        self._table = table

    def _try_write_results(self) -> None:
        try:
            self._write_results()
        except BaseException as exc:  # run() writes them again on its own thread, where the error is raised
            log.debug("writing the results while Ray stops: %s", exc)

    def _on_ray(self, jobs: list[Job]) -> None:
        ray = import_ray()
        local = self.address is None
        previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        started = time.monotonic()
        self.mark("ray init")
        node = None
        try:
            try:
                if local:
                    node = start_local_node(local_cpus())
                    if node is not None:
                        self.mark("ray node started")
                        # after the node: its processes are forked from here (and Ray's own start of them
                        # then connects, which waits on them)
                        threading.Thread(target=_import_plotting, name="import-matplotlib", daemon=True).start()
                        try:
                            ray.init(address=node.address, log_to_driver=False, logging_level=logging.ERROR)
                        except Exception as exc:
                            log.debug("connecting to the lean node: %s; ray.init starts the usual one", exc)
                            stop_local_node(node)
                            node = None
                    if node is None:
                        ray.init(address="local", num_cpus=local_cpus(), include_dashboard=False,
                                 log_to_driver=False, logging_level=logging.ERROR, _system_config=RAY_SYSTEM_CONFIG)
                else:
                    ray.init(address=self.address, log_to_driver=False, logging_level=logging.ERROR)
            except Exception as exc:
                raise TiFusionError(f"cannot start Ray{'' if local else ' at ' + self.address}: "
                                    f"{' '.join(str(exc).split())[:300]}") from None
            finally:  # ray.init sets its own SIGTERM handler: the CLI's stops the batch as Ctrl-C does
                for s, handler in previous.items():
                    if handler is not None:
                        signal.signal(s, handler)
            self.ray_start_s = round(time.monotonic() - started, 3)
            self.mark("ray ready")
            self._schedule(ray, jobs)
        finally:  # also after a Ctrl-C during ray.init: what it started goes
            self.mark("ray shutdown")
            # the records are final: the table and plot are written while Ray's processes stop
            writer = self._writer = threading.Thread(target=self._try_write_results, name="batch-results",
                                                     daemon=True)
            writer.start()
            try:
                ray.shutdown()
                if node is not None:
                    stop_local_node(node)
                self.mark("ray down")
            finally:
                writer.join()

    def _schedule(self, ray, jobs: list[Job]) -> None:
        total = ray.cluster_resources()
        cpus, gpus = float(total.get("CPU", 0)), float(total.get("GPU", 0))
        for j in jobs:
            if j.threads > cpus or j.gpus > gpus:
                raise InputError(self.manifest.path,
                                 f"job {j.name} asks Ray for {j.threads} CPUs and {j.gpus:g} GPUs; the cluster has "
                                 f"{cpus:g} CPUs and {gpus:g} GPUs")
        slots = min(len(jobs), self.max_jobs or len(jobs), max(1, int(cpus // min(j.threads for j in jobs))))
        self.say(f"{len(jobs)} jobs on Ray ({'local, ' if self.address is None else self.address + ', '}"
                 f"{cpus:g} CPUs{f', {gpus:g} GPUs' if gpus else ''}), at most {slots} at once; "
                 f"results in {self.folder}/results.md")
        remote = ray.remote(run_job)
        pending = longest_first(jobs)
        running: dict = {}  # ref -> (job, started)
        progress = _Progress(len(self.manifest.jobs), self.say if self.progress else None)
        progress.done = self.counts["skipped_done"]
        progress.failed = self.counts["kept_failed"]
        walls: list[float] = []
        try:
            while pending or running:
                used_cpu = sum(j.threads for j, _ in running.values())
                used_gpu = sum(j.gpus for j, _ in running.values())
                while pending and len(running) < (self.max_jobs or len(jobs)) and (
                        not running or (used_cpu + pending[0].threads <= cpus and used_gpu + pending[0].gpus <= gpus)):
                    job = pending.pop(0)
                    self.mark("task submitted", job.name)  # before: its worker may start it before .remote returns
                    ref = remote.options(num_cpus=job.threads, num_gpus=job.gpus, max_retries=0,
                                         name=f"ti-fusion-batch:{job.name}").remote(self._spec(job))
                    running[ref] = (job, time.monotonic())
                    used_cpu += job.threads
                    used_gpu += job.gpus
                progress.show(len(running), pending, running, walls, slots)
                ready, _ = ray.wait(list(running), num_returns=1, timeout=1.0)
                for ref in ready:
                    job, started = running.pop(ref)
                    rec = self._finish(ray, job, ref, started)
                    self.mark("result", job.name)
                    walls.append(rec["wall_s"] or time.monotonic() - started)
                    self.counts["ran"] += 1
                    if rec["status"] == results.DONE:
                        progress.done += 1
                    else:
                        progress.failed += 1
                        progress.note(f"{job.name} failed: {rec['error']}")
                    results.write_tables(self.folder, results.rows(self.folder, self.manifest.jobs))
            progress.show(0, [], {}, walls, slots)
            progress.end()
        except KeyboardInterrupt:
            progress.end()
            self._stop(ray, running)
            raise

    def taichi_threads(self, job: Job) -> int:
        """``--taichi-threads``; else locally, where the machine's CPUs are known, ``taichi_threads``; on a
        cluster, the job's threads."""
        if self.taichi is not None:
            return self.taichi
        return job.threads if self.address is not None else taichi_threads(job.threads, local_cpus())

    def _spec(self, job: Job) -> dict:
        return {"args": list(job.args), "run_dir": str(results.run_dir(self.folder, job.name).resolve()),
                "log": str(results.log_path(self.folder, job.name).resolve()),
                "env": job_env(job.threads, self.taichi_threads(job)),
                "cwd": os.getcwd(), "summary_fields": list(results.SUMMARY_FIELDS)}

    def _record(self, job: Job, **fields) -> dict:
        rec = {"job": job.name, "input": job.input, "variant": job.variant, "args": list(job.args),
               "threads": job.threads, "taichi_threads": self.taichi_threads(job), "gpus": job.gpus,
               "status": results.FAILED, "exit_code": None, "error": "", "wall_s": None, "summary": None,
               "finished": datetime.now().isoformat(timespec="seconds")}
        rec.update(fields)
        results.write_record(self.folder, rec)
        return rec

    def _finish(self, ray, job: Job, ref, started: float) -> dict:
        try:
            out = ray.get(ref)
        except ray.exceptions.RayError as exc:  # the worker or its node died, or run_job itself failed
            text = [ln for ln in str(exc).splitlines() if ln.strip()]
            return self._record(job, error=(text[-1] if text else type(exc).__name__)[:500],
                                wall_s=round(time.monotonic() - started, 3))
        ok = out["exit_code"] == 0 and out["summary"] is not None
        for event, at in (out.get("at") or {}).items():
            if at is not None:
                self.mark(event, job.name, at)
        return self._record(job, status=results.DONE if ok else results.FAILED, exit_code=out["exit_code"],
                            error=out["error"], wall_s=out["wall_s"], summary=out["summary"], host=out["host"])

    def _stop(self, ray, running: dict) -> None:
        """Ctrl-C: every running task stops its job (SIGTERM, then SIGKILL after the grace), the jobs are
        recorded as interrupted (a resume runs them again); a job that finished meanwhile keeps its row."""
        if not running:
            return
        self.say(f"stopping {len(running)} running jobs (each keeps what it has done; Ctrl-C again: at once)")
        for ref in running:
            ray.cancel(ref)
        ray.wait(list(running), num_returns=len(running), timeout=STOP_GRACE_S + 10)
        for ref, (job, started) in running.items():
            try:
                out = ray.get(ref, timeout=0)
            except Exception:  # cancelled (the usual case), or still stopping
                out = None
            if out is not None and out["exit_code"] == 0 and out["summary"] is not None:
                self._record(job, status=results.DONE, exit_code=0, error="", wall_s=out["wall_s"],
                             summary=out["summary"], host=out["host"])
            else:
                self._record(job, status=results.INTERRUPTED, error="stopped with the batch",
                             wall_s=round(time.monotonic() - started, 3))


class _Progress:
    """``batch: 3/6 done, 2 running, 1 failed, about 1 min 20 s left``: rewritten in place on a terminal,
    a line whenever the counts change otherwise."""

    def __init__(self, total: int, say):
        self.total, self.say = total, say
        self.done = self.failed = 0
        self.tty = sys.stdout.isatty()
        self._last = None
        self._open = False

    def show(self, n_running: int, pending, running: dict, walls: list[float], slots: int) -> None:
        if self.say is None:
            return
        line = f"batch: {self.done}/{self.total} done, {n_running} running, {self.failed} failed"
        counts = line
        if walls and (pending or running):
            mean = sum(walls) / len(walls)
            elapsed = sum(time.monotonic() - t for _, t in running.values())
            left = max(0.0, mean * (len(pending) + len(running)) - elapsed) / max(1, slots)
            line += f", about {_duration(left)} left"
        if self.tty:
            sys.stdout.write("\r" + line.ljust(78))
            sys.stdout.flush()
            self._open = True
        elif counts != self._last:
            self.say(line)
        self._last = counts

    def note(self, text: str) -> None:
        if self.say is None:
            return
        self.end()
        self.say(text)

    def end(self) -> None:
        if self._open:
            sys.stdout.write("\n")
            sys.stdout.flush()
            self._open = False


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"
