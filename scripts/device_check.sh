#!/usr/bin/env bash
# One command for a machine with a GPU: the kernel tests on cuda and vulkan, bench_launch.py, bench_host.py and
# bench_slam.py on cuda, cpu and vulkan, and one table of it all (docs/PERFORMANCE.md, host overhead).
#
#   scripts/device_check.sh pack [--frames N]     # here, with network: wheels and data into .device/
#   scripts/device_check.sh run  [--frames N] [--archs "cuda cpu vulkan"] [--out DIR] [--no-tests] [--jobs J]
#                                [--set SECTION.KEY=VALUE ...]
#   scripts/device_check.sh run --dry-run          # print the commands only
#
# The lent GPU machine has no network; its Python (3.12) has numpy, OpenCV, matplotlib, pytest and
# pytest-xdist. ``pack`` therefore gathers, on a machine with network, everything else the run needs into
# .device/ (git-ignored; carry it with the working tree, it stays under 64 MiB):
#   .device/wheels/  Taichi (cp312, manylinux x86_64) without taichi/_lib/c_api, its headers and assets (56 ->
#                    ~23 MB: the Python package never loads them), and the project's pure-Python
#                    dependencies that a slam run imports (mcap with zstandard and lz4, protobuf, the
#                    foxglove schemas, rosbags, PyYAML, ...), all for Python 3.12;
#   .device/data/    the first N frames (default 120) of ../shared/data/redkitchen-7scenes.
# ``run`` installs the wheels with ``pip --no-index --target .device/site`` where Taichi is not importable,
# puts that and the repository on PYTHONPATH, makes the ti_fusion.kernels mapping of an uninstalled copy
# (the link ti_fusion/kernels -> ../kernels, which setup.py's package-dir mapping stands for in an install;
# removed again at exit if it made it), then writes $OUT/device_check.md (default .device/out). --jobs J runs
# the kernel tests on J pytest-xdist workers (default 0: in one process). --set overrides the config of the
# bench_host and bench_slam runs (repeatable); where GTSAM is not importable (its wheel, 35 MB, does not fit
# beside the rest), the runs get --set slam.loop_closure=false and say so: with 120 frames no loop can be
# closed (candidates are 200 frames apart), but keyframes are not kept either.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
DEVICE="$ROOT/.device"
PY="${PYTHON:-python3}"
MODE="${1:-}"
shift || true
FRAMES=120
ARCHS="cuda cpu vulkan"
OUT="$DEVICE/out"
TESTS=1
JOBS=0
DRY=0
SETS=()
while [ $# -gt 0 ]; do
    case "$1" in
        --frames) FRAMES="$2"; shift 2 ;;
        --archs) ARCHS="$2"; shift 2 ;;
        --out) OUT="$2"; shift 2 ;;
        --no-tests) TESTS=0; shift ;;
        --jobs) JOBS="$2"; shift 2 ;;
        --dry-run) DRY=1; shift ;;
        --set) SETS+=("--set=$2"); shift 2 ;;
        *) echo "device_check.sh: unknown option $1 (see the head of scripts/device_check.sh)" >&2; exit 2 ;;
    esac
done

# Files of the kernel tests: those that take the ``arch`` fixture (tests/conftest.py).
KERNEL_TESTS="tests/kernels tests/tracking/test_icp.py tests/tracking/test_photometric.py tests/mapping/test_fusion.py
tests/mapping/test_corrections.py tests/mapping/test_mesh.py tests/loop/test_active_window.py tests/synthetic/test_scene.py"
# What a slam run imports beyond the lent machine's own packages (pure Python, or binary wheels for cp312).
WHEELS="mcap mcap-protobuf-support protobuf foxglove-schemas-protobuf foxglove-sdk zstandard lz4 rosbags ruamel.yaml
ruamel.yaml.clib pyyaml dill"

PLATFORMS="--platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux_2_27_x86_64
--platform manylinux_2_28_x86_64 --platform any"
pack() {
    local wheels="$DEVICE/wheels" tmp
    mkdir -p "$wheels" "$DEVICE/data"
    grep -qx '.device/' "$ROOT/.gitignore" 2>/dev/null || echo "device_check.sh: add .device/ to .gitignore" >&2
    tmp="$(mktemp -d)"
    # shellcheck disable=SC2086
    "$PY" -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 \
        $PLATFORMS \
        --implementation cp --dest "$tmp" "taichi==${TAICHI_VERSION:-$("$PY" -c \
        'import importlib.metadata as m; print(m.version("taichi"))')}"
    # Taichi without the C API, its headers, assets and examples, its core library stripped of symbols
    # (pip installs what the wheel holds; it does not check RECORD's hashes)
    (cd "$tmp" && for w in taichi-*.whl; do
        mkdir unpacked && (cd unpacked && "$PY" -m zipfile -e "../$w" .)
        rm -rf unpacked/taichi/_lib/c_api unpacked/taichi/assets unpacked/taichi/examples unpacked/taichi-*.data
        if command -v strip >/dev/null; then strip --strip-unneeded unpacked/taichi/_lib/core/*.so; fi
        "$PY" - "$wheels/$w" <<'PYEOF'
import os, sys, zipfile
with zipfile.ZipFile(sys.argv[1], "w", zipfile.ZIP_DEFLATED, compresslevel=9) as z:
    for top, _, files in os.walk("unpacked"):
        for f in files:
            path = os.path.join(top, f)
            z.write(path, os.path.relpath(path, "unpacked"))
PYEOF
        rm -rf unpacked
    done)
    # the versions of this environment, where it has them
    local pins=() p v
    for p in $WHEELS; do
        v="$("$PY" -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$p" 2>/dev/null || true)"
        pins+=("$p${v:+==$v}")
    done
    # shellcheck disable=SC2086
    "$PY" -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 $PLATFORMS \
        --implementation cp --dest "$wheels" "${pins[@]}"
    rm -rf "$tmp"
    local src="$ROOT/../shared/data/redkitchen-7scenes" dst="$DEVICE/data/redkitchen-$FRAMES"
    if [ -d "$src" ]; then
        mkdir -p "$dst"
        find "$src" -maxdepth 1 -type f ! -name 'frame-*' -exec cp {} "$dst/" \;
        for ((i = 0; i < FRAMES; i++)); do cp "$src"/frame-"$(printf %06d "$i")".* "$dst/"; done
    fi
    du -sh "$DEVICE"
}

MADE_LINK=0
run() {
    mkdir -p "$OUT"
    if [ "$DRY" = 1 ]; then
        say() { echo "+ $*"; }
    else
        say() { echo "+ $*" >&2; "$@"; }
    fi
    if ! "$PY" -c "import taichi" 2>/dev/null; then
        [ -d "$DEVICE/wheels" ] || { echo "device_check.sh: no Taichi and no .device/wheels (run 'pack' first)" >&2; exit 1; }
        say "$PY" -m pip install --quiet --no-index --no-deps --target "$DEVICE/site" "$DEVICE"/wheels/*.whl
    fi
    export PYTHONPATH="$DEVICE/site:$ROOT${PYTHONPATH:+:$PYTHONPATH}"
    if [ ! -e "$ROOT/ti_fusion/kernels" ]; then
        say ln -s ../kernels "$ROOT/ti_fusion/kernels"
        MADE_LINK=1
    fi
    trap 'if [ "$MADE_LINK" = 1 ]; then rm -f "$ROOT/ti_fusion/kernels"; fi' EXIT
    if ! "$PY" -c "import gtsam" 2>/dev/null; then
        echo "device_check.sh: GTSAM is not importable here: the runs go with --set slam.loop_closure=false" >&2
        SETS+=("--set=slam.loop_closure=false")
    fi
    local data=()
    [ -d "$DEVICE/data/redkitchen-$FRAMES" ] && data=("$DEVICE/data/redkitchen-$FRAMES")
    [ ${#data[@]} = 0 ] && [ -d "$ROOT/../shared/data/redkitchen-7scenes" ] && data=("$ROOT/../shared/data/redkitchen-7scenes")
    cd "$ROOT"
    if [ "$TESTS" = 1 ]; then
        for arch in cuda vulkan; do
            # shellcheck disable=SC2086
            say "$PY" -m pytest -q -p no:cacheprovider -n "$JOBS" $KERNEL_TESTS -k "$arch" -o addopts="" \
                2>&1 | tee "$OUT/tests_$arch.txt" | tail -1 || true
        done
    fi
    for arch in $ARCHS; do
        say "$PY" scripts/bench_launch.py --arch "$arch" --launches 3000 2>&1 | tee "$OUT/launch_$arch.txt" || true
        say "$PY" scripts/bench_host.py "${data[@]}" synthetic --frames "$FRAMES" --arch "$arch" ${SETS[@]+"${SETS[@]}"} \
            --top 16 --json "$OUT/host_$arch.json" 2>&1 | tee "$OUT/host_$arch.txt" || true
        for d in "${data[@]}" ""; do
            local tag; tag="$(basename "${d:-synthetic}")"
            say "$PY" scripts/bench_slam.py "$d" --frames "$FRAMES" --arch "$arch" --systems ti-fusion ${SETS[@]+"${SETS[@]}"} \
                --json "$OUT/slam_${arch}_$tag.json" 2>&1 | tee "$OUT/slam_${arch}_$tag.txt" || true
        done
    done
    [ "$DRY" = 1 ] && return 0
    "$PY" - "$OUT" <<'EOF' | tee "$OUT/device_check.md"
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
print("| arch | data | launches/frame | reads/frame | kernel ms | host ms | host ms (profiled) | processing ms "
      "| fps processing | busy | slam fps proc | slam fps loop | slam fps loop after warm-up | cores | read wait | ATE m |")
print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
for host in sorted(out.glob("host_*.json")):
    arch = host.stem[5:]
    for r in json.loads(host.read_text()):
        name = Path(r["data"]).name
        slam = out / f"slam_{arch}_{name}.json"
        s = next(iter(json.loads(slam.read_text())), {}) if slam.is_file() else {}
        if "error" in r:
            print(f"| {arch} | {name} | {r['error']} |")
            continue
        p, busy = r["processing_ms"], r.get("busy")  # host ms and busy as bench_host.py defines them
        cell = lambda x, f: "n/a" if x is None else format(x, f)
        print(f"| {arch} | {name} | {r['launches']:.1f} | {r['reads']:.2f} | {cell(r.get('kernel_ms'), '.2f')} | "
              f"{cell(r.get('host_ms'), '.2f')} | {cell(r.get('profiled_host_ms'), '.2f')} | {p:.2f} | {1e3 / p:.1f} | "
              f"{'n/a' if busy is None else format(100 * busy, '.0f') + ' %'} | {cell(s.get('fps'), '.1f')} | "
              f"{cell(s.get('fps_wall'), '.1f')} | {cell(s.get('fps_loop_steady'), '.1f')} | "
              f"{cell(s['cpu_s'] / s['process_s'] if s.get('cpu_s') and s.get('process_s') else None, '.2f')} | "
              f"{cell(100 * s['stages_s']['load'] / s['loop_s'] if 'load' in s.get('stages_s', {}) and s.get('loop_s') else None, '.1f')} % | "
              f"{cell(s.get('ate_rmse_m'), '.4f')} |")
for t in sorted(out.glob("launch_*.txt")):
    rows = [line for line in t.read_text().splitlines() if line.startswith("| ") and "µs" not in line]
    print(f"\nhost µs per launch on {t.stem[7:]} (bench_launch.py): " + "; ".join(
        " ".join(cell.strip() for cell in row.strip("|").split("|")) for row in rows))
for t in sorted(out.glob("tests_*.txt")):
    lines = t.read_text().strip().splitlines()
    print(f"\nkernel tests on {t.stem[6:]}: {lines[-1] if lines else 'no output'}")
EOF
}

case "$MODE" in
    pack) pack ;;
    run) run ;;
    *) echo "usage: scripts/device_check.sh pack|run [options] (see the head of the file)" >&2; exit 2 ;;
esac
