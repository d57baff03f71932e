"""The dataset formats' names: the registry that the config's checks and the loaders share (a leaf module,
so that the config need not import the loaders, which import the config)."""

FORMATS = ("tum", "iclnuim", "7scenes", "folder", "rosbag", "log", "synthetic")
