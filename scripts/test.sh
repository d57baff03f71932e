#!/usr/bin/env bash
# Set up .venv (first run only) and run the test suite (Taichi CPU backend; Vulkan too where present).
#   scripts/test.sh [pytest options]          (-n 0: one process; TI_FUSION_TEST_WORKERS=N: N processes)
#   scripts/test.sh --fast [pytest options]   the fast tier: every test not marked slow (the end-to-end runs),
#                                             on cpu only, which still launches every kernel (docs/CONTRIBUTING.md);
#                                             TI_FUSION_NO_VULKAN=0 / TI_FUSION_NO_CUDA=0 put the GPU backends back
# The suite runs in one process per core (at most 4), a test file per process at a time: most of its time
# is Taichi compiling kernels on one thread, so a second process uses the core the first leaves idle.
set -euo pipefail
source "$(dirname "$0")/setup_env.sh"
# Kernels compile with LLVM's fastest code generation (-O0; ti-fusion ships Taichi's default, 1): compiling,
# not running, is most of the suite's time (docs/CONTRIBUTING.md "The suite's time"). TI_OPT_LEVEL=1 tests
# what ships.
export TI_OPT_LEVEL="${TI_OPT_LEVEL:-0}"
WORKERS="${TI_FUSION_TEST_WORKERS:-$(python -c 'import os; print(min(4, len(os.sched_getaffinity(0))))')}"
SELECT=()
if [ "${1:-}" = "--fast" ]; then
    shift
    SELECT=(-m "not slow")
    # the kernels' cases on the GPU backends are a third of the tier's time (lavapipe runs them on the CPU)
    [ "${TI_FUSION_NO_VULKAN:-1}" = 0 ] && unset TI_FUSION_NO_VULKAN || export TI_FUSION_NO_VULKAN=1
    [ "${TI_FUSION_NO_CUDA:-1}" = 0 ] && unset TI_FUSION_NO_CUDA || export TI_FUSION_NO_CUDA=1
fi
exec python -m pytest -n "$WORKERS" --dist loadfile ${SELECT[@]+"${SELECT[@]}"} "$@"
