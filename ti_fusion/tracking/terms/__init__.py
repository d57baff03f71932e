"""The tracking terms ICP sums into its Gauss–Newton system, one ``TrackingTerm`` per file (``base.py``),
registered in ``TERMS``.

A term is one module here with a ``TrackingTerm`` subclass and one line in ``TERMS``: ``ICP`` builds one
instance of each, the fused ICP pass (``ti_fusion.kernels.icp``) unrolls the per-pixel functions of the terms a
frame uses into its one launch per iteration, and ``DenseSLAM`` asks each term whether a frame can use it
(docs/ARCHITECTURE.md, "How to add a tracking term").
"""

from __future__ import annotations

from importlib import import_module

from ti_fusion.tracking.terms.base import TrackingTerm

# module:class of each term, in the order of their sums in a pass. The first is the geometry, always on: its
# row count is the correspondences' (inliers), and the other terms' weights are relative to it.
TERMS: tuple[str, ...] = (
    "point_to_plane:PointToPlaneTerm",
    "photometric:PhotometricTerm",
)


def term_classes() -> list[type[TrackingTerm]]:
    """The registered terms' classes, in order (an entry with a dotted module path is imported as it is:
    a term defined outside this package, e.g. by a test)."""
    classes = []
    for entry in TERMS:
        module, name = entry.split(":")
        classes.append(getattr(import_module(module if "." in module else f"ti_fusion.tracking.terms.{module}"), name))
    return classes


def make_terms(config) -> list[TrackingTerm]:
    """One instance of every registered term for ``config`` (an ``ICPConfig``), in order; each checks its
    settings (ValueError)."""
    return [cls(config) for cls in term_classes()]
