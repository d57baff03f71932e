"""The input formats: one registry, format name → the ``Dataset`` class that reads it.

Adding a reader is its loader file in ``ti_fusion/io/datasets/`` plus one line here; the class itself says
the rest (``Dataset.detect``: the file that identifies its format; ``identified_by``: that file as the
"unrecognised layout" line names it; ``single_file``, ``replaceable_calibration``, ``reads_color_camera``).
The classes are named by import path and imported when first used, so that one format's import problem
cannot break the others, and so that the config, which checks ``dataset.format`` against these names, needs
no loader (a leaf module: the loaders import the config). Detection asks the formats in this order.
"""

LOADERS = {
    "tum": "ti_fusion.io.datasets.tum:TUMDataset",
    "iclnuim": "ti_fusion.io.datasets.iclnuim:ICLNUIMDataset",
    "7scenes": "ti_fusion.io.datasets.sevenscenes:SevenScenesDataset",
    "folder": "ti_fusion.io.datasets.folder:FolderDataset",
    "rosbag": "ti_fusion.io.datasets.rosbag:RosbagDataset",
    "log": "ti_fusion.io.datasets.runlog:RunLogDataset",
    "synthetic": "ti_fusion.io.datasets.synthetic:SyntheticDataset",
}

FORMATS = tuple(LOADERS)  # the names as registered here (the code asks LOADERS, which a test may extend)
