"""``ti-fusion slam DATA --map RUN_OR_MAP_DIR [--localize]``: a second session against a run's saved map. It finds
itself in the map and extends it, or with --localize tracks against it and leaves the saved map byte for byte as it
was; a session that never sees the mapped place exits with status 3 and its summary; a map of another camera or
image size is refused in one line naming both; --localize without --map is refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ti_fusion.cli.main import main
from ti_fusion.io.map_files import DATA, HEADER

TINY = ["--downsample", "4", "--quiet"]  # 160x120 synthetic frames


def _poses(run) -> list[str]:
    return [line for line in (run / "trajectory.tum").read_text().splitlines() if not line.startswith("#")]


@pytest.fixture
def tiny_map(cpu, tmp_path):
    out = tmp_path / "first"
    assert main(["slam", "--frames", "3", *TINY, "--out", str(out)]) == 0
    return out


def test_localize_needs_a_map(tmp_path, capsys):
    assert main(["slam", "--localize", "--frames", "1", *TINY, "--out", str(tmp_path / "run")]) == 2
    assert capsys.readouterr().err.strip() == ("ti-fusion slam: error: --localize tracks against a saved map: give it "
                                               "with --map RUN_OR_MAP_DIR")


@pytest.mark.slow
def test_a_map_of_another_image_size_is_refused_naming_both(tiny_map, tmp_path, capsys):
    capsys.readouterr()
    assert main(["slam", "--map", str(tiny_map), "--frames", "1", "--downsample", "2", "--quiet",
                 "--out", str(tmp_path / "second")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "at 160x120" in err[0] and "at 320x240" in err[0], err


@pytest.mark.slow
def test_a_session_that_never_sees_the_mapped_place_exits_3_with_its_frames_not_localised(tiny_map, tmp_path, capsys):
    second = tmp_path / "second"
    capsys.readouterr()
    assert main(["slam", "--map", str(tiny_map), "--scene", "wall", "--frames", "2", *TINY,
                 "--out", str(second)]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none of the 2 frames found itself in the map" in err[0] and "not localised" in err[0]
    assert "--unfound map-anyway" in err[0]
    summary = json.loads((second / "summary.json").read_text())
    assert summary["unlocalised_frames"] == 2 and summary["localised_at"] is None and "error" in summary
    assert not (second / "trajectory.tum").exists()  # no frame got a pose
    # with --unfound map-anyway it maps on in its own frame after map.find_frames frames
    again = tmp_path / "again"
    assert main(["slam", "--map", str(tiny_map), "--scene", "wall", "--frames", "3", *TINY, "--unfound",
                 "map-anyway", "--set", "map.find_frames=1", "--out", str(again)]) == 0
    summary = json.loads((again / "summary.json").read_text())
    assert summary["own_map_at"] == 1 and summary["unlocalised_frames"] == 1
    assert len(_poses(again)) == 2


@pytest.mark.slow
def test_a_session_finds_itself_extends_the_map_or_localises_leaving_it_unchanged(cpu, tmp_path, capsys):
    first = tmp_path / "first"
    size = ["--downsample", "2", "--quiet"]
    assert main(["slam", "--frames", "20", *size, "--out", str(first)]) == 0
    saved = {name: (first / "map" / name).read_bytes() for name in (HEADER, DATA)}
    localised = tmp_path / "localised"
    assert main(["slam", "--map", str(first), "--localize", "--start", "8", "--frames", "4", *size,
                 "--out", str(localised)]) == 0
    assert {name: (first / "map" / name).read_bytes() for name in (HEADER, DATA)} == saved
    assert not (localised / "map").exists()  # a localisation writes no map
    summary = json.loads((localised / "summary.json").read_text())
    assert summary["session"] == "localize" and summary["localised_at"] == 8 and summary["unlocalised_frames"] == 0
    assert summary["ate_rmse_m"] < 0.01 and summary["surfels"] == json.loads(
        (first / "summary.json").read_text())["surfels"]
    extended = tmp_path / "extended"
    assert main(["slam", "--map", str(first), "--start", "8", "--frames", "4", *size, "--out", str(extended)]) == 0
    summary = json.loads((extended / "summary.json").read_text())
    assert summary["session"] == "extend" and summary["localised_at"] == 8
    assert summary["saved_map"]["keyframes"] > json.loads((first / "summary.json").read_text())["keyframes"]
    assert len(_poses(extended)) == 4
    # map_trajectory.tum: both sessions' frames in the map's frame (no loop moved the first's: as it wrote them),
    # and the extended map carries them on
    from ti_fusion.io.trajectory import read_tum
    from ti_fusion.slam.saved_map import load_map

    stamps, poses = read_tum(extended / "map_trajectory.tum")
    first_stamps, first_poses = read_tum(first / "trajectory.tum")
    own_stamps, own_poses = read_tum(extended / "trajectory.tum")
    np.testing.assert_allclose(stamps, np.concatenate([first_stamps, own_stamps]))
    np.testing.assert_allclose(np.asarray(poses), np.concatenate([first_poses, own_poses]), atol=1e-5)
    assert summary["map_trajectory"] == {"frames": 24, "earlier_sessions_frames": 20}
    saved = load_map(extended)
    assert len(saved.trajectory) == 24 and saved.trajectory.sessions == 2
    assert saved.trajectory.session.tolist() == [0] * 20 + [1] * 4
    assert not (localised / "map_trajectory.tum").exists()
