"""The benchmarks' OpenCV peer (scripts/benchlib.py ``OpenCVOdometry``): whichever API this cv2 has, the
motion it returns is the one the benchmarks compare with ours (Rt · p_source = p_target)."""

import numpy as np
import pytest

from ti_fusion.config import SynthConfig
from ti_fusion.geometry import invert, make_pose, pose_error, so3_exp


@pytest.mark.parametrize("kind", ["depth", "rgbd"])
def test_opencv_odometry_recovers_a_known_motion(cpu, script, kind):
    benchlib = script("benchlib")
    cv2 = pytest.importorskip("cv2")
    if not (hasattr(cv2, "Odometry") or hasattr(cv2, "rgbd")):
        pytest.skip(f"OpenCV {cv2.__version__} has no RGB-D odometry")
    from ti_fusion.synthetic.scene import SyntheticSequence

    seq = SyntheticSequence(SynthConfig())
    G = make_pose(so3_exp(np.radians([0.8, -0.6, 0.4])), [0.01, -0.008, 0.012])  # source → target
    pose = seq.poses[40]
    (ds, cs), (dt, ct) = seq.render(pose, seed=1, downsample=2), seq.render(pose @ invert(G), seed=2, downsample=2)
    K = seq.intrinsics.downsampled(2)
    odometry = benchlib.OpenCVOdometry(kind, K, 4.0)
    src = odometry.prepare(ds, benchlib.grey_of(cs))
    dst = odometry.prepare(dt, benchlib.grey_of(ct))
    ok, Rt = odometry.compute(src, dst)
    assert ok
    rot_deg, trans_m = pose_error(Rt, G)
    assert rot_deg < 0.3 and trans_m < 0.005, (rot_deg, trans_m)
    # and not the inverse: the motion is far larger than the error bound
    assert pose_error(invert(Rt), G)[1] > 0.02
