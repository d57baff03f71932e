#!/usr/bin/env bash
# Build the wheel, install it into a fresh venv outside the checkout, and run a short SLAM with it:
# proves that an installed ti-fusion holds every package it imports (kernels included).
#   scripts/check_wheel.sh          (PYTHON=python3.x to pick the interpreter)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${PYTHON:-python3}"
WORK="$(mktemp -d "${TMPDIR:-/tmp}/ti-fusion-wheel.XXXXXX")"
trap 'rm -rf "$WORK"' EXIT
echo "check_wheel: building the wheel" >&2
"$PY" -m pip wheel --quiet --no-deps --no-build-isolation -w "$WORK/dist" "$ROOT" >&2 2>/dev/null \
    || "$PY" -m pip wheel --quiet --no-deps -w "$WORK/dist" "$ROOT" >&2
WHEEL="$(ls "$WORK"/dist/ti_fusion-*.whl)"
echo "check_wheel: installing $(basename "$WHEEL") into a fresh venv" >&2
"$PY" -m venv "$WORK/venv"
"$WORK/venv/bin/python" -m pip install --quiet --upgrade pip >&2
"$WORK/venv/bin/python" -m pip install --quiet "$WHEEL" >&2
cd "$WORK"  # outside the checkout: nothing can be imported from the source tree
"$WORK/venv/bin/python" - <<'PY'
import pathlib, ti_fusion, ti_fusion.kernels
for module in (ti_fusion, ti_fusion.kernels):
    assert "site-packages" in module.__file__, f"{module.__name__} imported from {module.__file__}"
PY
"$WORK/venv/bin/ti-fusion" slam --frames 5 --downsample 4 --quiet --out "$WORK/run" >&2
test "$(grep -vc '^#' "$WORK/run/trajectory.tum")" = 5
test -s "$WORK/run/summary.json" && test -s "$WORK/run/log.mcap"
echo "check_wheel: the installed wheel ran 'ti-fusion slam' outside the checkout: ok" >&2
