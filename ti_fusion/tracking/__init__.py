"""Camera tracking: point-to-plane ICP (``ICP``), its 6×6 solve, and ORB + PnP feature odometry."""
