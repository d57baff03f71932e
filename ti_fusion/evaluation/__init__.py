"""Trajectory accuracy (ATE, RPE, as evo computes them) and trajectory plots."""
