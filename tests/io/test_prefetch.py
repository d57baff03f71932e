"""Reading frames ahead (``ti_fusion.io.prefetch``) on a thread and in reader processes: order, the
bound on reading ahead, a reading error raised at its own frame, a reader process that dies, the readers
stopped however the loop ends (Ctrl-C, SIGTERM and SIGHUP to the process group included) with no process
and no shared memory left, a caller's script without a ``__main__`` guard, and the pipeline's results
unchanged."""

from __future__ import annotations

import copy
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from ti_fusion.backend import current_backend
from ti_fusion.config import Config
from ti_fusion.errors import InputError
from ti_fusion.io.datasets import open_dataset
from ti_fusion.io.mcap_log import read_log
from ti_fusion.io.outputs import RunDir
from ti_fusion.io.frame_workers import ReaderDied
from ti_fusion.io.prefetch import Prefetcher, read_mode, reader_count
from ti_fusion.io.trajectory import read_tum
from ti_fusion.slam.pipeline import READ_AHEAD, SLAMPipeline
from tests.conftest import terminal_signals
from tests.io import readers

DEADLINE_S = 60  # a bound for a broken test, not a timing any test depends on


def _readers() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "ti-fusion-reader"]


class Items:
    """A dataset of ``n`` items (item i is i); reading item ``bad`` raises ``error``. Counts the reads."""

    def __init__(self, n: int, bad: int = -1, error: BaseException | None = None, slow_every: int = 0):
        self.n, self.bad, self.error, self.slow_every = n, bad, error, slow_every
        self.reads = 0
        self.read = []  # the indices read, in the order their reads began
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> int:
        with self._lock:  # several readers may count at once
            self.reads += 1
            self.read.append(i)
        if i == self.bad:
            raise self.error
        if self.slow_every and i % self.slow_every == 0:
            time.sleep(0.001)  # reads of uneven length: the order must not depend on them
        return i


@pytest.mark.parametrize("mode", ["thread", "inline"])
def test_frames_come_in_order(mode):
    data = Items(200, slow_every=7)
    with Prefetcher(data, ahead=3, mode=mode) as frames:
        got = [(i, item) for i, item, read_ms in frames]
    assert got == [(i, i) for i in range(200)]
    assert not _readers()


@pytest.mark.parametrize("mode", ["thread", "inline"])
def test_an_error_is_raised_at_its_frame_after_the_frames_before(mode):
    error = InputError("frame-000005.depth.png", "cannot read the image")
    done = []
    with pytest.raises(InputError) as caught:
        with Prefetcher(Items(10, bad=5, error=error), ahead=3, mode=mode) as frames:
            for i, item, _ in frames:
                done.append(item)
    assert caught.value is error and str(caught.value) == "frame-000005.depth.png: cannot read the image"
    assert done == [0, 1, 2, 3, 4]
    assert not _readers()


def test_the_reader_stays_at_most_ahead_frames_in_front():
    data = Items(100)
    with Prefetcher(data, ahead=3) as frames:
        deadline = time.monotonic() + DEADLINE_S
        while data.reads < 3 and time.monotonic() < deadline:
            time.sleep(0.001)
        assert 3 <= data.reads <= 4  # three waiting in the queue, at most one more in the reader's hand
        next(frames)
    assert data.reads <= 5
    assert not _readers()


def test_an_interrupted_loop_stops_the_reader():
    """Ctrl-C (and SIGTERM, which the CLI turns into the same exception) in the loop: the reader thread
    ends too, also when it is blocked on a full queue."""
    data = Items(10_000)
    with pytest.raises(KeyboardInterrupt):
        with Prefetcher(data, ahead=2) as frames:
            for i, _, _ in frames:
                if i == 3:
                    raise KeyboardInterrupt
    assert not _readers()
    assert data.reads <= 3 + 1 + 2 + 1  # what was consumed, then at most the queue and one read


def test_an_interrupt_raised_while_reading_reaches_the_loop():
    """A KeyboardInterrupt out of the reading itself (a test's stand-in for a signal during a read) ends
    the loop at that frame, as an error does."""
    with pytest.raises(KeyboardInterrupt):
        with Prefetcher(Items(10, bad=4, error=KeyboardInterrupt()), ahead=2) as frames:
            for _ in frames:
                pass
    assert not _readers()


def test_how_a_dataset_is_read_and_by_how_many():
    class Files:
        concurrent_reads = True

    class Bag:
        concurrent_reads = False

    assert reader_count(3, Files()) == 3 and reader_count(3, Bag()) == 1 and reader_count(0, Bag()) == 1
    assert reader_count(0, object()) == 1  # a dataset that does not say: one reader
    assert 1 <= reader_count(0, Files()) <= 4
    assert read_mode(readers.Items(3)) == "processes"
    assert read_mode(Items(3)) == "thread"  # not marked reads_in_process (and holds a lock: does not pickle)

    class Rendered:
        renders_on_taichi = True

    assert read_mode(Rendered()) == "inline"
    synthetic = readers.Synthetic()  # rendered in a reader process on the CPU; on a GPU by the loop's backend
    assert read_mode(synthetic, "cpu") == "processes"
    assert read_mode(synthetic, "cuda") == read_mode(synthetic, "vulkan") == read_mode(synthetic) == "inline"


# --------------------------------------------------------------------------------------------------
# Reader processes
# --------------------------------------------------------------------------------------------------
def _children(parent: int | None = None) -> set[int]:
    """The pids of the live child processes of ``parent`` (default: this process; Linux /proc)."""
    parent, found = os.getpid() if parent is None else parent, set()
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()  # after the command name, which may hold spaces
            if int(fields[1]) == parent and fields[0] != "Z":
                found.add(int(entry))
    return found


def _memfds() -> int:
    """How many memfd files this process holds open."""
    count = 0
    for fd in os.listdir("/proc/self/fd"):
        try:
            count += os.readlink(f"/proc/self/fd/{fd}").startswith("/memfd:ti-fusion-frames")
        except OSError:
            pass
    return count


def _named_shm() -> set[str]:
    """The names of multiprocessing.shared_memory blocks in /dev/shm (its psm_ prefix): the way a pool's frames
    could outlive it, where its anonymous memfd cannot. Not every name there: /dev/shm is the machine's, and
    other processes (the suite's other worker, Ray, a semaphore of multiprocessing) add and remove names of
    their own at any moment."""
    return {name for name in os.listdir("/dev/shm") if name.startswith("psm_")}


@pytest.fixture
def clean():
    """Every test of reader processes ends with none of them left, no receiver thread, no memfd open and /dev/shm
    as it was."""
    before, shm = _children(), _named_shm()
    yield
    assert _children() <= before
    assert not [t for t in threading.enumerate() if t.name.startswith("ti-fusion-receiver")]
    assert _memfds() == 0
    assert _named_shm() <= shm


@pytest.mark.parametrize("workers", [1, 3])
def test_processes_hand_out_every_frame_in_order(clean, tmp_path, workers):
    log = tmp_path / "reads"
    data = readers.Items(120, log=log, slow_every=3)
    with Prefetcher(data, ahead=3, workers=workers, mode="processes") as frames:
        got = [(i, item) for i, item, read_ms in frames]
    assert got == [(i, i) for i in range(120)]
    assert sorted(readers.read_indices(log)) == list(range(120))  # each frame read once


def test_frames_cross_through_shared_memory_bit_for_bit(clean):
    """Depth, colour and the rest of each frame arrive as read; a frame whose colour does not fit its slot
    (frame 5: four times the pixels) is handed over whole."""
    data = readers.Frames(12, big=5)
    with Prefetcher(data, ahead=3, workers=2, mode="processes") as frames:
        assert _memfds() >= 1 and len(_children()) >= 2  # (mmap holds a duplicate of the descriptor)
        for i, frame, _ in frames:
            want = data[i]
            assert frame.index == i and frame.meta == {"i": i} and not hasattr(frame, "_shm")
            np.testing.assert_array_equal(frame.depth, want.depth)
            np.testing.assert_array_equal(frame.color, want.color)
            np.testing.assert_array_equal(frame.gt_pose, want.gt_pose)
            assert frame.depth.flags.writeable and frame.color.flags.writeable


def test_frames_are_taken_from_the_readers_on_the_receiver_thread(clean, monkeypatch):
    """The caller's thread neither waits for a reader's message nor copies a frame out of the shared memory: the
    receiver thread does, while the caller works on the frame before; leaving the loop early stops it."""
    from ti_fusion.io.frame_workers import WorkerPool

    takers, take = set(), WorkerPool.take
    monkeypatch.setattr(WorkerPool, "take", lambda *a: takers.add(threading.current_thread().name) or take(*a))
    data = readers.Frames(12)
    with Prefetcher(data, ahead=3, workers=2, mode="processes") as frames:
        for i, frame, _ in frames:
            np.testing.assert_array_equal(frame.depth, data[i].depth)
            if i == 8:
                break
    assert takers and all(name.startswith("ti-fusion-receiver") for name in takers)
    assert not [t for t in threading.enumerate() if t.name.startswith("ti-fusion-receiver")]


def test_processes_stay_within_ahead_of_the_caller(clean, tmp_path, monkeypatch):
    """No process is asked for frame j before the caller has begun to take frame j − ahead (frame 0 is read by the
    caller itself, while the processes start), and no process reads a frame it was not asked for. Each request is
    checked as it is made, against the frames the caller has begun to take by then, so no interleaving of the
    receiver thread, the processes and the caller can hide a request made too early."""
    from ti_fusion.io.frame_workers import WorkerPool

    log = tmp_path / "reads"
    data = readers.Items(100, log=log)
    ahead = 3
    taking = 0  # the caller's next() calls begun: frames 0 .. taking - 1 taken or being taken
    asked: list[tuple[int, int]] = []  # (frame, taking) at each request, in the order made
    request = WorkerPool.request

    def recorded(pool, i, worker, slot):
        asked.append((i, taking))  # before the request is sent: a process reads nothing not recorded here
        request(pool, i, worker, slot)

    monkeypatch.setattr(WorkerPool, "request", recorded)
    with Prefetcher(data, ahead=ahead, workers=2, mode="processes") as frames:
        assert asked == [(1, 0), (2, 0), (3, 0)]  # asked for before the caller took any
        deadline = time.monotonic() + DEADLINE_S  # a bound for a broken test, not a timing the test depends on
        while len(readers.read_indices(log)) < ahead and time.monotonic() < deadline:
            time.sleep(0.01)
        assert sorted(readers.read_indices(log)) == [1, 2, 3]
        for k in range(1, 12):
            taking = k
            assert next(frames)[0] == k - 1
            assert set(readers.read_indices(log)) <= {0} | {i for i, _ in asked}  # (0: the caller's own read)
    too_early = [(i, k) for i, k in asked if i > max(k, 1) - 1 + ahead]
    assert not too_early, too_early
    assert [i for i, _ in asked] == list(range(1, 11 + ahead))  # each asked for once, in order
    assert set(readers.read_indices(log)) <= {0} | {i for i, _ in asked}


def test_reader_processes_are_out_of_reach_of_the_terminals_signals(clean):
    """Readers run in a session of their own from the moment they start: a Ctrl-C that the terminal sends to
    the caller's process group while a reader's interpreter is still starting (before it could ignore
    SIGINT) would kill it and end the run as a failed read instead of an interrupted one."""
    others = _children()  # (an earlier test's process still ending in this worker is not a reader)
    with Prefetcher(readers.Items(20), ahead=3, workers=2, mode="processes") as frames:
        pids = _children() - others
        assert len(pids) == 2
        assert all(os.getsid(pid) == pid and os.getpgid(pid) != os.getpgid(0) for pid in pids)
        assert [item for _, item, _ in frames] == list(range(20))


@pytest.mark.parametrize("workers", [1, 3])
def test_in_processes_an_error_comes_at_its_frame_and_nothing_after_it(clean, workers):
    error = InputError("frame-000007.depth.png", "cannot read the image")
    done = []
    with pytest.raises(InputError) as caught:
        with Prefetcher(readers.Items(50, bad=7, error=error, slow_every=2), ahead=3, workers=workers,
                        mode="processes") as frames:
            for i, item, _ in frames:
                done.append(item)
    assert str(caught.value) == "frame-000007.depth.png: cannot read the image" and done == list(range(7))


def test_an_interrupt_raised_in_a_reader_process_reaches_the_loop(clean):
    with pytest.raises(KeyboardInterrupt):
        with Prefetcher(readers.Items(10, bad=4, error=KeyboardInterrupt()), ahead=2, mode="processes") as frames:
            for _ in frames:
                pass


def test_an_interrupted_loop_stops_every_process(clean, tmp_path):
    log = tmp_path / "reads"
    with pytest.raises(KeyboardInterrupt):
        with Prefetcher(readers.Items(10_000, log=log), ahead=3, workers=3, mode="processes") as frames:
            for i, _, _ in frames:
                if i == 5:
                    raise KeyboardInterrupt
    assert max(readers.read_indices(log)) <= 5 + 3


def test_a_pool_closed_while_a_frame_is_copied_out_of_it_closes(clean):
    """A second Ctrl-C inside ``Prefetcher.close`` cuts its wait for the receiver thread, and the pool then closes
    while that thread may still copy a frame out of the shared memory: the close ends as usual (no BufferError
    instead of the stop), and the memory goes once the copy's view does."""
    from ti_fusion.io.frame_workers import WorkerPool

    pool = WorkerPool(readers.Items(4), workers=1, slots=2, slot_bytes=4096)
    view = np.frombuffer(pool._buf, dtype=np.uint8, count=8)  # the receiver's view, mid-copy
    pool.close()
    assert not pool.pids
    del view  # (the clean fixture: no memfd left open)


def test_a_reader_process_that_dies_ends_the_loop_at_its_frame(clean):
    """A reader killed (SIGKILL, as by the OOM killer) at frame 5: the frames before it come out, then
    ``ReaderDied`` names the process and the frame, and the other processes are stopped."""
    done = []
    with pytest.raises(ReaderDied, match=r"the frame reader process \(pid \d+\) was killed by SIGKILL while "
                                         r"reading frame 5"):
        with Prefetcher(readers.Items(40, die_at=5), ahead=3, workers=2, mode="processes") as frames:
            for i, item, _ in frames:
                done.append(item)
    assert done == [0, 1, 2, 3, 4]


def test_synthetic_frames_rendered_in_a_reader_process_are_the_frames_rendered_here(clean, cpu):
    """The synthetic sequence rendered in a reader process (its own Taichi on the CPU) gives the frames of
    the loop's own renderer bit for bit, frame 0 included (rendered there too, so that its renderer
    compiles beside the loop); the reader's first kernel launches are counted with this process's."""
    from ti_fusion.frontend import CLOCK

    dataset = readers.Synthetic.from_config(Config().synth, stride=37, stop=148)  # four frames, full size
    launches = len(CLOCK.launches)
    with Prefetcher.for_dataset(dataset, ahead=3, arch="cpu") as frames:
        got = list(frames)
    assert [i for i, _, _ in got] == [0, 1, 2, 3]
    assert "render_kernel" in [name for name, _, _ in CLOCK.launches[launches:]]
    for i, frame, _ in got:
        here = dataset[i]
        assert frame.index == here.index and frame.timestamp == here.timestamp and frame.meta == here.meta
        np.testing.assert_array_equal(frame.depth, here.depth)
        np.testing.assert_array_equal(frame.color, here.color)
        np.testing.assert_array_equal(frame.gt_pose, here.gt_pose)


@pytest.mark.parametrize("how", ["error", "killed"])
def test_a_failing_renderer_process_ends_the_run_at_its_frame(cpu, clean, tmp_path, how):
    """A synthetic frame that cannot be rendered (an error in the reader process, or the process killed):
    the run ends at that frame with its error, keeping the trajectory and a finalised log of the frames
    before it, and leaves no process behind."""
    cfg = _config()
    dataset = readers.Synthetic.from_config(cfg.synth, downsample=4, stop=8)
    dataset.bad, dataset.die_at = (5, -1) if how == "error" else (-1, 5)
    run = RunDir("slam", tmp_path / "run")
    expected = (InputError, "frame 5: cannot render the frame") if how == "error" else \
        (ReaderDied, r"the frame reader process \(pid \d+\) was killed by SIGKILL while reading frame 5")
    with pytest.raises(expected[0], match=expected[1]):
        SLAMPipeline(dataset, cfg, run, current_backend(), show_progress=False).run()
    stamps, _ = read_tum(run.file("trajectory.tum"))
    assert len(stamps) == 5
    log = read_log(run.file("log.mcap"))
    assert log.complete and len(log.stats) == 5


SCRIPT = """
import os, sys
sys.path.insert(0, {root!r})
from ti_fusion.io.prefetch import Prefetcher
from tests.io import readers

with Prefetcher(readers.Items(200_000, sleep_s=0.002), ahead=3, workers=2, mode="processes") as frames:
    for i, item, _ in frames:
        if i == 20:
            print("ready", flush=True)
        if i == {stop_at}:
            break
print("done", i, flush=True)
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except OSError:
        return False


@pytest.mark.parametrize("how", ["script", "-c"])
def test_reader_processes_from_a_script_without_a_main_guard(tmp_path, how):
    """The Python API from a script with no ``if __name__ == "__main__"`` guard, and from code with no file
    (``python -c``, as a notebook's cell): the readers run nothing of the caller's script."""
    root = str(Path(__file__).resolve().parents[2])
    code = SCRIPT.format(root=root, stop_at=60)
    args = [sys.executable, str(tmp_path / "run.py")] if how == "script" else [sys.executable, "-c", code]
    (tmp_path / "run.py").write_text(code)
    done = subprocess.run(args, capture_output=True, text=True, timeout=DEADLINE_S * 5, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[-1] == "done 60" and done.stdout.count("ready") == 1


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=["SIGINT", "SIGTERM", "SIGHUP"])
def test_a_signal_to_the_whole_process_group_leaves_no_reader_behind(tmp_path, signum):
    """Ctrl-C in a terminal signals every process of the group, readers included: they ignore it, the
    caller stops them and ends; SIGTERM (the caller's default action: it dies at once) and SIGHUP leave
    readers that see their socket close and end."""
    root = str(Path(__file__).resolve().parents[2])
    (tmp_path / "run.py").write_text(SCRIPT.format(root=root, stop_at=10**9))
    shm = _named_shm()
    proc = subprocess.Popen([sys.executable, str(tmp_path / "run.py")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path, start_new_session=True,
                            preexec_fn=terminal_signals)
    try:
        assert proc.stdout.readline().strip() == "ready"
        workers = _children(proc.pid)
        assert len(workers) == 2
        os.killpg(proc.pid, signum)
        proc.communicate(timeout=DEADLINE_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode in (-signum, 128 + signum, 1), proc.returncode
    deadline = time.monotonic() + DEADLINE_S
    while any(_alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(_alive(p) for p in workers)
    assert _named_shm() <= shm


# --------------------------------------------------------------------------------------------------
# In the pipeline: frames read on the thread give the results of frames read on the loop's own thread
# --------------------------------------------------------------------------------------------------
class InMemory:
    """Frames rendered beforehand, served from memory as a file-based loader serves them: read on the
    pipeline's reader thread (``renders_on_taichi`` False). Frame ``bad`` fails to read."""

    renders_on_taichi = False

    def __init__(self, dataset, bad: int = -1):
        self.dataset, self.bad = dataset, bad
        self.frames = [dataset[i] for i in range(len(dataset))]

    def __getattr__(self, name):
        return getattr(self.dataset, name)

    def __len__(self):
        return len(self.frames)

    def __getitem__(self, i):
        if i == self.bad:
            raise InputError(f"frame-{i:06d}.depth.png", "cannot read the image")
        return copy.deepcopy(self.frames[i])


def _config() -> Config:
    cfg = Config()
    cfg.dataset.downsample = 4
    cfg.dataset.stop = 8
    cfg.log.progress = False
    return cfg


@pytest.mark.slow
def test_pipeline_reads_ahead_with_the_same_results(cpu, tmp_path):
    """Frames read on the loop's thread, on the reader thread and by three reader processes (frames of a
    dataset that pickles, ``reads_in_process``): the same trajectory and map; the summary says how."""
    from ti_fusion.io.datasets.arrays import FrameList

    cfg = _config()
    children = _children()  # (another test's processes in this worker are not the readers)
    dataset = open_dataset(cfg.dataset, cfg.synth)
    rendered = SLAMPipeline(dataset, cfg, RunDir("slam", tmp_path / "rendered"), current_backend(),
                            show_progress=False).run()  # the frames rendered in a reader process
    dataset.renders_in_process = False
    inline = SLAMPipeline(dataset, cfg, RunDir("slam", tmp_path / "inline"), current_backend(),
                          show_progress=False).run()
    threaded = SLAMPipeline(InMemory(dataset), cfg, RunDir("slam", tmp_path / "threaded"), current_backend(),
                            show_progress=False).run()
    cfg3 = _config()
    cfg3.dataset.read_workers = 3
    files = FrameList([dataset[i] for i in range(len(dataset))], name="synthetic")
    files.reads_in_process = files.concurrent_reads = True
    three = SLAMPipeline(files, cfg3, RunDir("slam", tmp_path / "three"), current_backend(), show_progress=False).run()
    (_, a), (_, b), (_, c), (_, d) = (read_tum(tmp_path / name / "trajectory.tum")
                                      for name in ("inline", "threaded", "three", "rendered"))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, c)
    np.testing.assert_array_equal(a, d)
    assert inline["surfels"] == threaded["surfels"] == three["surfels"] == rendered["surfels"]
    assert [(s["read_mode"], s["read_workers"]) for s in (inline, threaded, three, rendered)] == \
        [("inline", 0), ("thread", 1), ("processes", 3), ("processes", 1)]
    for s in (inline, threaded, three, rendered):
        assert s["fps_wall"] > 0 and s["frames"] == 8 and "read" in s["ms_per_stage"]
        assert s["first_frame_s"] <= s["second_frame_s"] <= s["process_s"]
    assert not _readers() and _children() <= children


@pytest.mark.slow
def test_pipeline_keeps_the_frames_before_a_bad_one(cpu, tmp_path):
    cfg = _config()
    run = RunDir("slam", tmp_path / "run")
    with pytest.raises(InputError, match="frame-000005.depth.png: cannot read"):
        SLAMPipeline(InMemory(open_dataset(cfg.dataset, cfg.synth), bad=5), cfg, run, current_backend(),
                     show_progress=False).run()
    stamps, _ = read_tum(run.file("trajectory.tum"))
    assert len(stamps) == 5
    log = read_log(run.file("log.mcap"))
    assert log.complete and len(log.stats) == 5
    assert not _readers()


# --------------------------------------------------------------------------------------------------
# The command line: a stop or a dead reader process ends the run as before, leaving no process behind
# --------------------------------------------------------------------------------------------------
def _folder(root: Path, n: int = 40) -> list[str]:
    """A plain folder of ``n`` textured 80×60 frames; the ``ti-fusion vo`` arguments that read it."""
    import cv2

    (root / "depth").mkdir(parents=True)
    (root / "rgb").mkdir()
    rng = np.random.default_rng(0)
    texture = cv2.resize(rng.integers(0, 256, (30, 40, 3), dtype=np.uint8), (160, 120), interpolation=cv2.INTER_NEAREST)
    for i in range(n):
        cv2.imwrite(str(root / "depth" / f"{i:06d}.png"), np.full((60, 80), 1500 + i, np.uint16))
        cv2.imwrite(str(root / "rgb" / f"{i:06d}.png"), texture[i % 20:i % 20 + 60, i % 40:i % 40 + 80])
    return ["vo", str(root), "--format", "folder", "--depth-scale", "1000", "--intrinsics", "60,60,40,30", "--quiet"]


def _at_frame(monkeypatch, k: int, action) -> None:
    """``action()`` when the vo step is handed its frame ``k`` (in the loop, while the readers read ahead)."""
    from ti_fusion.slam.vo_step import VOStep

    original = VOStep.register_frame

    def register_frame(self, frame):
        if frame.index == k:
            action()
        return original(self, frame)

    monkeypatch.setattr(VOStep, "register_frame", register_frame)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_stop_ends_the_run_with_its_readers(clean, tmp_path, capsys, monkeypatch, signum):
    from ti_fusion.cli.main import main

    args = _folder(tmp_path / "data")
    _at_frame(monkeypatch, 3, lambda: os.kill(os.getpid(), signum))
    out = tmp_path / "run"
    # Ctrl-C as in a terminal: pytest-xdist's workers ignore SIGINT, and a run leaves an ignored Ctrl-C ignored
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert main([*args, "--out", str(out)]) == 128 + signum
    finally:
        signal.signal(signal.SIGINT, previous)
    log = read_log(out / "log.mcap")
    assert log.complete and len(log.stats) == 3
    assert not (out / "summary.json").exists()
    if (out / "trajectory.tum").exists():  # (the frames that got a pose)
        assert len(read_tum(out / "trajectory.tum")[0]) <= 3


def test_a_reader_process_killed_ends_the_run_in_one_line(clean, tmp_path, capsys, monkeypatch):
    from ti_fusion.cli.main import main

    args = _folder(tmp_path / "data")
    others = _children()  # only the run's reader processes are killed
    _at_frame(monkeypatch, 3, lambda: [os.kill(pid, signal.SIGKILL) for pid in _children() - others])
    out = tmp_path / "run"
    assert main([*args, "--out", str(out)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("ti-fusion vo: error: the frame reader process (pid "), err
    k = int(err[0].split("while reading frame ")[1])
    log = read_log(out / "log.mcap")
    # the frames it had read before it was killed still come out: those asked for by frame 3
    assert 4 <= k <= 3 + READ_AHEAD + 1 and log.complete and len(log.stats) == k
