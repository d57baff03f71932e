"""Small text tables (trajectories, calibration and association files): rows of numbers with the line
that holds them, so that an error names the line."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ti_fusion.errors import InputError


def read_table(path: str | Path, what: str = "file") -> list[tuple[int, list[str]]]:
    """Whitespace-separated rows of a text file as (line number, fields), skipping blanks and # comments."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, f"{what} not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read {what}: {exc}") from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith("#"):
            rows.append((lineno, line.replace(",", " ").split()))
    return rows


def parse_floats(fields: list[str], path: Path, lineno: int) -> np.ndarray:
    try:
        values = np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError:
        raise InputError(path, f"line {lineno}: expected numbers, got {' '.join(fields)!r}") from None
    if not np.all(np.isfinite(values)):
        raise InputError(path, f"line {lineno}: contains NaN or infinite values")
    return values
