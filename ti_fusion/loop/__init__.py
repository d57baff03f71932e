"""Loop closure: keyframes, place recognition, verification, the pose graph and the correction (docs/LOOP_CLOSURE.md)."""
