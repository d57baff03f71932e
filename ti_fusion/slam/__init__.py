"""The SLAM system (``DenseSLAM.register_frame``) and the pipeline that owns the run loop."""
