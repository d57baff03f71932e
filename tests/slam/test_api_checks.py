"""The Python API checks what it is given: ``DenseSLAM.register_frame`` refuses, with one
``InputError`` naming the frame, what its map cannot take (another camera, another size, depth in the wrong
units, timestamps that are not finite or do not increase), ``rgbd_frame`` undistorts a calibrated camera's
images, and ``SLAMPipeline`` runs once, checks a ``FrameList`` before its first frame and keeps the outputs
of the frames done when a later frame is refused."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ti_fusion.camera import Intrinsics
from ti_fusion.config import Config
from ti_fusion.errors import InputError
from ti_fusion.io.datasets import FrameList, rgbd_frame
from ti_fusion.io.trajectory import read_tum

W, H = 160, 120
K = Intrinsics(fx=131.25, fy=131.25, cx=79.5, cy=59.5, width=W, height=H)  # the synthetic camera at 160x120
FRAMES = 6


@pytest.fixture(scope="module")
def frames():
    """The synthetic room at 160x120, FRAMES frames, as ``rgbd_frame``s (metres, no range cut)."""
    from ti_fusion.backend import init_backend
    from ti_fusion.config import SynthConfig
    from ti_fusion.synthetic.scene import SyntheticSequence

    init_backend("cpu")
    seq = SyntheticSequence(SynthConfig(frames=FRAMES, width=W, height=H, fx=K.fx))
    assert seq.intrinsics == K
    out = []
    for i in range(FRAMES):
        depth, rgb = seq.frame(i)
        out.append(rgbd_frame(depth, K, color=rgb, timestamp=seq.timestamps[i], index=i, gt_pose=seq.poses[i],
                              depth_max=None))
    return out


def _slam(intrinsics: Intrinsics = K):
    from ti_fusion.slam.dense import DenseSLAM

    cfg = Config()
    cfg.log.progress = False
    return DenseSLAM(cfg, intrinsics)


def _refused(slam, frame, message: str) -> str:
    with pytest.raises(InputError, match=message) as info:
        slam.register_frame(frame)
    assert "\n" not in str(info.value)
    return str(info.value)


# --------------------------------------------------------------------------------------------------
# Class 2: another camera, another size
# --------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_frame_of_another_camera_or_size_is_refused_at_register_frame(cpu, frames):
    slam = _slam()
    other = dataclasses.replace(K, fx=200.0, fy=200.0)
    line = _refused(slam, dataclasses.replace(frames[0], intrinsics=other),
                    r"frame 0: intrinsics fx 200 fy 200 cx 79.5 cy 59.5 differ from the DenseSLAM's fx 131.25")
    assert "one camera per DenseSLAM" in line
    small = rgbd_frame(frames[0].depth[::2, ::2], K.downsampled(2), timestamp=0.0)
    _refused(slam, small, r"frame 0: 80x60 images, the DenseSLAM's intrinsics are for 160x120")
    assert slam.register_frame(frames[0]).status == "init"  # the refusals left no trace


@pytest.mark.slow
@pytest.mark.parametrize("change, message", [
    (dict(cx=5000.0, cy=-300.0), r"DenseSLAM intrinsics: principal point \(5000, -300\) is outside the 160x120 image"),
    (dict(fx=1e-6, fy=1e-6), r"DenseSLAM intrinsics: fx 1e-06, fy 1e-06 give a 180° x 180° field of view at "
                             r"160x120: outside 20° to 170°"),
])
def test_intrinsics_that_cannot_be_the_cameras_are_refused(cpu, frames, change, message):
    bad = dataclasses.replace(K, **change)
    _refused(_slam(bad), dataclasses.replace(frames[0], intrinsics=bad), message)


# --------------------------------------------------------------------------------------------------
# Class 3: depth in the wrong units
# --------------------------------------------------------------------------------------------------
def test_depth_in_metres_given_a_millimetre_scale_is_refused_at_the_first_frame(cpu, frames):
    metres = frames[0].depth.copy()
    frame = rgbd_frame(metres, K, depth_scale=1000, timestamp=0.0)  # every depth 0.5 to 3 mm
    line = _refused(_slam(), frame, r"frame 0: 95 % of its depth is under 5 cm \(.* mm to .* mm, median .* mm\), "
                                    "nearer than any RGB-D camera measures, so the depth is not in metres")
    assert "1000 for millimetres, none for float metres" in line
    with pytest.raises(InputError, match="depth of type uint16: a Frame's depth is float metres"):
        _slam().register_frame(dataclasses.replace(frames[0], depth=(metres * 1000).astype(np.uint16)))
    nan = metres.copy()
    nan[3, :5] = np.nan
    _refused(_slam(), dataclasses.replace(frames[0], depth=nan), "frame 0: depth has 5 NaN, infinite or negative")


# --------------------------------------------------------------------------------------------------
# Classes 7 and 9: timestamps
# --------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_timestamps_must_be_finite_and_increasing(cpu, frames):
    """Each refused frame leaves the run as it was (one run for the three: a DenseSLAM compiles its kernels)."""
    slam = _slam()
    slam.register_frame(dataclasses.replace(frames[0], timestamp=0.0))
    for stamp, message in ((float("nan"), r"frame 1: timestamp nan is not a finite number of seconds"),
                           (-5.0, r"frame 1: timestamp -5.000000 is not after frame 0's 0.000000: timestamps must "
                                  r"increase"),
                           (0.0, r"frame 1: timestamp 0.000000 is not after frame 0's 0.000000")):
        _refused(slam, dataclasses.replace(frames[1], timestamp=stamp), message)
    assert slam.register_frame(dataclasses.replace(frames[1], timestamp=0.1)).tracked


def test_a_frame_list_is_checked_before_its_first_frame(cpu, frames, tmp_path):
    from ti_fusion.io.outputs import RunDir
    from ti_fusion.slam.pipeline import SLAMPipeline

    same = [dataclasses.replace(f, timestamp=100.0) for f in frames]
    out = tmp_path / "run"
    with pytest.raises(InputError, match=r"frame 1: timestamp 100.000000 is not after frame 0's 100.000000"):
        SLAMPipeline(FrameList(same), Config(), RunDir("slam", out), None, show_progress=False).run()
    assert not (out / "log.mcap").exists()  # refused before anything was written


class _LateNaN:
    """Frames made on demand (a lazy sequence), whose frame ``bad`` has a NaN timestamp."""

    def __init__(self, frames, bad: int):
        self.frames, self.bad = frames, bad

    def __len__(self):
        return len(self.frames)

    def __getitem__(self, i):
        frame = self.frames[i]
        return dataclasses.replace(frame, timestamp=float("nan")) if i == self.bad else frame


@pytest.mark.slow
def test_a_late_refusal_keeps_the_outputs_of_the_frames_done(cpu, frames, tmp_path):
    from ti_fusion.io.outputs import RunDir
    from ti_fusion.slam.pipeline import SLAMPipeline

    out = tmp_path / "run"
    cfg = Config()
    cfg.log.progress = False
    with pytest.raises(InputError, match="frame 4: timestamp nan is not a finite number of seconds"):
        SLAMPipeline(FrameList(_LateNaN(frames, 4)), cfg, RunDir("slam", out), None, show_progress=False).run()
    stamps, _ = read_tum(out / "trajectory.tum")
    assert len(stamps) == 4
    for name in ("log.mcap", "map.ply", "map_color.png", "trajectory.png"):
        assert (out / name).is_file(), name


@pytest.mark.slow
def test_a_pipeline_runs_once(cpu, frames, tmp_path):
    from ti_fusion.io.outputs import RunDir
    from ti_fusion.slam.pipeline import SLAMPipeline

    cfg = Config()
    cfg.log.progress = False
    pipeline = SLAMPipeline(FrameList(frames[:3]), cfg, RunDir("slam", tmp_path / "run"), None, show_progress=False)
    assert pipeline.run()["frames"] == 3
    with pytest.raises(InputError, match="this pipeline has run already: one run per Pipeline"):
        pipeline.run()
    assert len(read_tum(tmp_path / "run" / "trajectory.tum")[0]) == 3


# --------------------------------------------------------------------------------------------------
# Class 1 from Python: a calibrated camera's frames are undistorted
# --------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_rgbd_frame_undistorts_a_camera_with_distortion_and_skew(cpu, frames):
    distorted = dataclasses.replace(K, skew=4.0, distortion=(0.25, -0.8, 0.001, 0.002, 0.9),
                                    distortion_model="plumb_bob")
    frame = rgbd_frame(frames[0].depth, distorted, color=frames[0].color, timestamp=0.0)
    assert frame.intrinsics == K and frame.intrinsics.pinhole
    assert not np.array_equal(frame.depth, frames[0].depth)
    # nearest neighbour: every depth is one of the input's, none an average across an edge
    assert np.isin(frame.depth[frame.depth > 0], frames[0].depth).all()
    assert _slam().register_frame(frame).status == "init"


# --------------------------------------------------------------------------------------------------
# The process around the API: threads, Taichi started again, the types a user passes
# --------------------------------------------------------------------------------------------------
_THREADS_SCRIPT = r'''
import json, queue, sys, threading
import numpy as np
from ti_fusion.backend import init_backend
from ti_fusion.camera import Intrinsics
from ti_fusion.config import Config, SynthConfig
from ti_fusion.io.datasets import rgbd_frame
from ti_fusion.slam.dense import DenseSLAM
from ti_fusion.synthetic.scene import SyntheticSequence

K = Intrinsics(fx=131.25, fy=131.25, cx=79.5, cy=59.5, width=160, height=120)
init_backend("cpu")
seq = SyntheticSequence(SynthConfig(frames=3, width=160, height=120, fx=K.fx))
frames = [rgbd_frame(seq.frame(i)[0], K, color=seq.frame(i)[1], timestamp=seq.timestamps[i], index=i, depth_max=None)
          for i in range(3)]
out = {}

# 1. made on the main thread, fed from a callback's thread
slam = DenseSLAM(Config(), K)
def callback():
    try:
        slam.register_frame(frames[0])
        out["other_thread"] = "ran"
    except Exception as exc:
        out["other_thread"] = f"{type(exc).__name__}: {exc}"
t = threading.Thread(target=callback, name="ros-callback"); t.start(); t.join()

# 2. the documented way: one worker thread starts Taichi, makes the DenseSLAM and registers every frame
#    that other threads put into a queue
inbox, statuses = queue.Queue(), []
def worker():
    init_backend("cpu")
    mine = DenseSLAM(Config(), K)
    while (frame := inbox.get()) is not None:
        statuses.append(mine.register_frame(frame).status)
w = threading.Thread(target=worker); w.start()
for f in frames:  # each put from its own thread, as a driver's callbacks would, in order
    p = threading.Thread(target=inbox.put, args=(f,)); p.start(); p.join()
inbox.put(None); w.join()
out["worker"] = statuses

# 3. Taichi started again (on the main thread), then an older DenseSLAM used
init_backend("cpu")
try:
    slam.register_frame(frames[1])
    out["stale"] = "ran"
except Exception as exc:
    out["stale"] = f"{type(exc).__name__}: {exc}"
print(json.dumps(out))
'''


@pytest.mark.slow
def test_threads_and_a_second_init_backend(tmp_path):
    """register_frame from another thread than Taichi's says in one line how to do it (Taichi 1.7 allocates
    fields only on the thread that ran ti.init), and that way (one worker thread fed by a queue) works; a
    DenseSLAM made before init_backend was called again is refused, not a segmentation fault."""
    import json
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", _THREADS_SCRIPT], capture_output=True, text=True, timeout=600,
                          cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["other_thread"].startswith("BackendMisuse: DenseSLAM.register_frame called on thread 'ros-callback'")
    assert "all on one thread" in out["other_thread"] and "\n" not in out["other_thread"]
    assert len(out["worker"]) == 3 and out["worker"][0] == "init" and out["worker"][1:] == ["ok", "ok"]
    assert out["stale"].startswith("BackendMisuse: DenseSLAM.register_frame: made before Taichi was started again")


def test_colour_is_copied_from_a_reused_buffer():
    """A camera driver reuses one colour buffer: each frame keeps the colour it was made with."""
    buffer = np.zeros((30, 40, 3), np.uint8)
    frames = []
    for i in range(3):
        buffer[:] = 10 * (i + 1)
        frames.append(rgbd_frame(np.ones((30, 40)), Intrinsics(30.0, 30.0, 19.5, 14.5, 40, 30), color=buffer, index=i))
    assert [int(f.color[0, 0, 0]) for f in frames] == [10, 20, 30]


def test_frames_without_index_or_timestamp_say_what_to_pass(frames):
    """rgbd_frame's defaults give every frame index 0 at 0 s: the second frame names what to pass."""
    slam = _slam()
    plain = [dataclasses.replace(f, index=0, timestamp=0.0) for f in frames[:2]]
    slam.register_frame(plain[0])
    with pytest.raises(InputError, match=r"^frame 0: the same index as the frame before it .* rgbd_frame\(\.\.\., "
                                         r"index=i, timestamp=seconds\)"):
        slam.register_frame(plain[1])
    with pytest.raises(InputError, match="the same index as the frame before it"):
        from ti_fusion.slam.checks import _check_frame_list

        _check_frame_list(FrameList(plain))


@pytest.mark.parametrize("field, value, message", [
    ("fx", "525", r"Intrinsics fx='525': expected a number of pixels, got str"),
    ("width", "640", r"Intrinsics width='640': expected a whole number of pixels, got str"),
    ("height", 479.5, r"Intrinsics height=479.5: expected a whole number"),
])
def test_intrinsics_of_the_wrong_type_are_one_line(field, value, message):
    values = dict(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)
    values[field] = value
    with pytest.raises(InputError, match=message):
        Intrinsics(**values)
    assert Intrinsics(fx=np.float64(525), fy=525, cx=319.5, cy=239.5, width=np.int64(640), height=480.0).height == 480
