"""Everything read or written: dataset loaders, MCAP logs, PLY, TUM trajectories, a run's output folder."""
