"""Reading frames ahead on background threads (``ti_fusion.io.prefetch``): order, a reading error raised
at its own frame, the threads stopped however the loop ends, several readers at once, and the pipeline's
results unchanged."""

from __future__ import annotations

import copy
import sys
import threading
import time

import numpy as np
import pytest

from ti_fusion.backend import current_backend
from ti_fusion.config import Config
from ti_fusion.errors import InputError
from ti_fusion.io.datasets import open_dataset
from ti_fusion.io.mcap_log import read_log
from ti_fusion.io.outputs import RunDir
from ti_fusion.io.prefetch import Prefetcher, reader_threads
from ti_fusion.io.trajectory import read_tum
from ti_fusion.slam.pipeline import SLAMPipeline

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


@pytest.mark.parametrize("threaded", [True, False], ids=["thread", "inline"])
def test_frames_come_in_order(threaded):
    data = Items(200, slow_every=7)
    interval = sys.getswitchinterval()
    with Prefetcher(data, ahead=3, threaded=threaded) as frames:
        got = [(i, item) for i, item, read_ms in frames]
    assert got == [(i, i) for i in range(200)]
    assert not _readers()
    assert sys.getswitchinterval() == interval  # the reader's shorter GIL switch interval is given back


@pytest.mark.parametrize("threaded", [True, False], ids=["thread", "inline"])
def test_an_error_is_raised_at_its_frame_after_the_frames_before(threaded):
    error = InputError("frame-000005.depth.png", "cannot read the image")
    done = []
    with pytest.raises(InputError) as caught:
        with Prefetcher(Items(10, bad=5, error=error), ahead=3, threaded=threaded) as frames:
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


@pytest.mark.parametrize("workers", [2, 4])
def test_several_readers_hand_out_every_frame_in_order(workers):
    data = Items(300, slow_every=3)
    interval = sys.getswitchinterval()
    with Prefetcher(data, ahead=3, workers=workers) as frames:
        assert len(_readers()) == workers
        got = [(i, item) for i, item, read_ms in frames]
    assert got == [(i, i) for i in range(300)]
    assert sorted(data.read) == list(range(300))  # each frame read once
    assert not _readers()
    assert sys.getswitchinterval() == interval


def test_several_readers_stay_within_ahead_of_the_caller():
    """No reader starts frame j before the caller has taken frame j − ahead: at most ``ahead`` frames (at
    least one per reader) are read or being read beyond what was handed out."""
    data = Items(100)
    with Prefetcher(data, ahead=2, workers=4) as frames:  # ahead raised to one per reader: 4
        deadline = time.monotonic() + DEADLINE_S
        while data.reads < 4 and time.monotonic() < deadline:
            time.sleep(0.001)
        time.sleep(0.05)
        assert sorted(data.read) == [0, 1, 2, 3]
        for k in range(10):
            next(frames)
            time.sleep(0.01)
            assert max(data.read) <= k + 4
    assert not _readers()


@pytest.mark.parametrize("workers", [1, 3])
def test_with_several_readers_an_error_comes_at_its_frame_and_nothing_after_it(workers):
    error = InputError("frame-000007.depth.png", "cannot read the image")
    done = []
    with pytest.raises(InputError) as caught:
        with Prefetcher(Items(50, bad=7, error=error, slow_every=2), ahead=3, workers=workers) as frames:
            for i, item, _ in frames:
                done.append(item)
    assert caught.value is error and done == list(range(7))
    assert not _readers()


def test_an_interrupted_loop_stops_every_reader():
    data = Items(10_000)
    with pytest.raises(KeyboardInterrupt):
        with Prefetcher(data, ahead=3, workers=3) as frames:
            for i, _, _ in frames:
                if i == 5:
                    raise KeyboardInterrupt
    assert not _readers()
    assert data.reads <= 6 + 3


def test_reader_threads_by_setting_and_dataset():
    class Files:
        concurrent_reads = True

    class Bag:
        concurrent_reads = False

    assert reader_threads(3, Files()) == 3 and reader_threads(3, Bag()) == 1 and reader_threads(0, Bag()) == 1
    assert reader_threads(0, object()) == 1  # a dataset that does not say: one reader
    assert 1 <= reader_threads(0, Files()) <= 4


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


def test_pipeline_reads_ahead_with_the_same_results(cpu, tmp_path):
    """Frames read on the loop's thread, on one reader and on three readers at once (a dataset of files,
    ``concurrent_reads``): the same trajectory and map; the summary says how many threads read."""
    cfg = _config()
    dataset = open_dataset(cfg.dataset, cfg.synth)
    inline = SLAMPipeline(dataset, cfg, RunDir("slam", tmp_path / "inline"), current_backend(),
                          show_progress=False).run()
    threaded = SLAMPipeline(InMemory(dataset), cfg, RunDir("slam", tmp_path / "threaded"), current_backend(),
                            show_progress=False).run()
    cfg3 = _config()
    cfg3.dataset.read_threads = 3
    files = InMemory(dataset)
    files.concurrent_reads = True
    three = SLAMPipeline(files, cfg3, RunDir("slam", tmp_path / "three"), current_backend(), show_progress=False).run()
    (_, a), (_, b), (_, c) = (read_tum(tmp_path / name / "trajectory.tum") for name in ("inline", "threaded", "three"))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, c)
    assert inline["surfels"] == threaded["surfels"] == three["surfels"]
    assert (inline["read_threads"], threaded["read_threads"], three["read_threads"]) == (0, 1, 3)
    for s in (inline, threaded, three):
        assert s["fps_wall"] > 0 and s["frames"] == 8 and "read" in s["ms_per_stage"]
        assert s["first_frame_s"] <= s["second_frame_s"] <= s["process_s"]
    assert not _readers()


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
