"""The benchmark scripts' command lines: a bad option is one line naming it (exit 2), a short run prints
its table. Speeds themselves are the scripts' output, never asserted here."""

import subprocess
import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def run(name: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPTS / name), *args], capture_output=True, text=True,
                          timeout=300)


def test_bench_host_names_a_bad_override():
    out = run("bench_host.py", "synthetic", "--set", "icp.colour_weight=0")
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [out.stderr.strip()]  # one line
    assert "bench_host.py: --set" in out.stderr and "colour_weight" in out.stderr
    assert "Traceback" not in out.stderr


def test_bench_host_names_a_bad_repeat():
    out = run("bench_host.py", "synthetic", "--repeat", "0")
    assert out.returncode == 2 and out.stderr.strip() == "bench_host.py: --repeat 0: give at least 1"


def test_bench_launch_prints_a_row_per_argument_kind():
    out = run("bench_launch.py", "--arch", "cpu", "--launches", "3")
    assert out.returncode == 0, out.stderr
    rows = [line for line in out.stdout.splitlines() if line.startswith("| ") and "µs" not in line]
    assert len(rows) == 8 and any("common.data_oriented" in row for row in rows)
    assert all(len(row.split("|")) == 7 for row in rows)  # both paths' wall and CPU columns
    bad = run("bench_launch.py", "--launches", "0")
    assert bad.returncode == 2 and "--launches must be at least 1" in bad.stderr


CABINET = Path(__file__).resolve().parents[2] / "shared" / "data" / "tum-fr3-cabinet-keyframes"


@pytest.mark.slow
def test_bench_real_prints_its_tables_on_real_keyframes():
    if not (CABINET / "depth.txt").is_file():
        import pytest

        pytest.skip(f"real data not found at {CABINET}")
    out = run("bench_real.py", str(CABINET), "--frames", "3", "--open3d-runs", "0", "--pairs", "2")
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    slam = [line for line in lines if line.strip().startswith("ti-fusion slam (defaults)")]
    assert len(slam) == 1 and slam[0].split()[3] == "3"  # frames
    pairs = [line for line in lines if "→" in line]
    assert len(pairs) == 2 and pairs[0].split()[0] == "1→0"
    assert any(line.strip().startswith("median") for line in lines)


def test_bench_real_names_a_bad_option():
    out = run("bench_real.py", "--pairs", "-1")
    assert out.returncode == 2 and out.stderr.strip() == "bench_real.py: --pairs -1: give at least 0"


def test_bench_map_io_prints_its_table():
    out = run("bench_map_io.py", "--surfels", "3000", "--repeat", "1")
    assert out.returncode == 0, out.stderr
    rows = [line for line in out.stdout.splitlines() if line.startswith("| ")]
    assert len(rows) == 9 and any(r.startswith("| bytes per surfel") and "| 56.0 |" in r for r in rows)
    bad = run("bench_map_io.py", "--repeat", "0")
    assert bad.returncode == 2 and bad.stderr.strip() == "bench_map_io.py: --repeat 0: give at least 1"


def test_bench_cold_start_names_a_bad_option():
    out = run("bench_cold_start.py", "--rounds", "0")
    assert out.returncode == 2 and out.stderr.strip() == "bench_cold_start.py: --rounds 0: give at least 1"
    out = run("bench_cold_start.py", "--baseline", "no-such-ref-here")
    assert out.returncode == 2 and out.stderr.strip().startswith("bench_cold_start.py: --baseline no-such-ref-here: ")
    assert "Traceback" not in out.stderr


def test_bench_sessions_names_a_bad_case():
    out = run("bench_sessions.py", "--cases", "redkitchen,kitchen")
    assert out.returncode == 2 and "--cases: no case 'kitchen' (redkitchen, loop)" in out.stderr


def test_bench_kernel_tasks_names_a_bad_option():
    for args, line in ((("--frames", "2"), "--frames 2: give at least 3"),
                       (("--repeat", "-1"), "--repeat -1: give at least 0"),
                       (("/no/such/folder",), "/no/such/folder: not a folder (give a dataset folder)")):
        out = run("bench_kernel_tasks.py", *args)
        assert out.returncode == 2 and out.stderr.strip() == f"bench_kernel_tasks.py: {line}"


@pytest.mark.slow
@pytest.mark.skipif(not (CABINET / "depth.txt").is_file(), reason=f"real data not found at {CABINET}")
def test_bench_kernel_tasks_prints_its_tables():
    out = run("bench_kernel_tasks.py", str(CABINET), "--frames", "4", "--repeat", "1", "--top", "3")
    assert out.returncode == 0, out.stderr
    assert "| ms per frame | launches per frame | task |" in out.stdout
    assert "| stage | task | fastest ms |" in out.stdout and "| render | " in out.stdout
