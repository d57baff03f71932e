#!/usr/bin/env bash
# Set up .venv (first run only) and run the main job: dense SLAM on the embedded synthetic sequence.
#   scripts/run.sh [--arch cpu|cuda|vulkan|auto] [any further ti-fusion slam options]
set -euo pipefail
source "$(dirname "$0")/setup_env.sh"
# the command keeps this process: it counts its time from here, not from the set-up above (ti_fusion/timing.py)
TI_FUSION_EXEC_AT="$(date +%s.%N)" exec ti-fusion slam "$@"
