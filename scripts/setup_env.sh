# Sourced by run.sh and test.sh: create .venv if missing and install ti-fusion into it (editable).
# Re-installs only when pyproject.toml changed since the last install.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-python3}"
if ! "$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else 1)' 2>/dev/null; then
    echo "ti-fusion needs Python >= 3.10 (found: $("$PY" --version 2>&1)); set PYTHON=/path/to/python3.10+" >&2
    exit 1
fi
if [ ! -x .venv/bin/python ]; then
    echo "creating .venv with $("$PY" --version)" >&2
    "$PY" -m venv .venv
fi
EXTRAS="${TI_FUSION_EXTRAS:-test}"
STAMP=".venv/.ti-fusion-installed-$EXTRAS"
if [ ! -f "$STAMP" ] || [ pyproject.toml -nt "$STAMP" ]; then
    echo "installing ti-fusion[$EXTRAS] into .venv (first run takes a minute)" >&2
    .venv/bin/python -m pip install --quiet --upgrade pip >&2
    .venv/bin/python -m pip install --quiet -e ".[$EXTRAS]" >&2
    touch "$STAMP"
fi
# the package's modules byte-compiled where missing or stale, as pip does for an installed package: an editable
# install leaves it to the first import, which PYTHONDONTWRITEBYTECODE=1 turns off, and every run would then
# compile the ~125 modules again (docs/PERFORMANCE.md, "The warm run's fixed cost, again"); a failure is not this
# script's (under set -e it would end test.sh and run.sh silently): a syntax error is the import's to name, and a
# read-only checkout just runs uncompiled
.venv/bin/python -m compileall -q ti_fusion kernels >/dev/null || true
export PATH="$ROOT/.venv/bin:$PATH"
