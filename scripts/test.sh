#!/usr/bin/env bash
# Set up .venv (first run only) and run the test suite (Taichi CPU backend; Vulkan too where present).
#   scripts/test.sh [pytest options]
set -euo pipefail
source "$(dirname "$0")/setup_env.sh"
exec python -m pytest "$@"
