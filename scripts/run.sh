#!/usr/bin/env bash
# Set up .venv (first run only) and run the main job: dense SLAM on the embedded synthetic sequence.
#   scripts/run.sh [--arch cpu|cuda|vulkan|auto] [any further ti-fusion slam options]
set -euo pipefail
source "$(dirname "$0")/setup_env.sh"
exec ti-fusion slam "$@"
