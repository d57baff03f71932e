"""The run's saved map (map/ in the run folder, or --save-map DIR): written at the end of every slam run, read
back as the run's map; saving changes no pose; a --save-map folder holding other files is refused before the
first frame; an option of slam only; like map.ply, not written after a stop."""

from __future__ import annotations

import json

import pytest

from ti_fusion.cli.main import main
from ti_fusion.config import Config
from ti_fusion.io.map_files import DATA, HEADER
from ti_fusion.sinks.map import MapSink
from ti_fusion.sinks.saved_map import SavedMapSink

TINY = ["--frames", "4", "--downsample", "4", "--quiet"]  # 160x120 synthetic frames


def test_it_is_kept_after_a_stop_exactly_when_map_ply_is():
    assert SavedMapSink.on_stop == MapSink.on_stop and SavedMapSink.commands == ("slam",)
    assert SavedMapSink.wanted("slam", Config(), {}) and not SavedMapSink.wanted("vo", Config(), {})


def test_save_map_is_an_option_of_slam_only(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["vo", "--save-map", str(tmp_path / "m")])
    assert "unrecognized arguments: --save-map" in capsys.readouterr().err


def test_no_save_map_turns_it_off_and_is_refused_beside_save_map(tmp_path, capsys):
    from ti_fusion.cli.main import build_parser
    from ti_fusion.sinks import chosen, make_sinks

    parser, _ = build_parser()
    outputs = chosen(parser.parse_args(["slam", "--no-save-map"]), "slam")
    assert outputs == {"saved_map": False} and chosen(parser.parse_args(["slam"]), "slam") == {}
    assert not any(isinstance(s, SavedMapSink) for s in make_sinks("slam", Config(), outputs))
    with pytest.raises(SystemExit):
        main(["vo", "--no-save-map"])
    assert "unrecognized arguments: --no-save-map" in capsys.readouterr().err
    assert main(["slam", *TINY, "--no-save-map", "--save-map", str(tmp_path / "m"), "--out", str(tmp_path / "r")]) == 2
    assert capsys.readouterr().err.strip() == (f"ti-fusion slam: error: --no-save-map writes no saved map and "
                                               f"--save-map {tmp_path / 'm'} names where it goes: give one of them")
    assert not (tmp_path / "m").exists()


@pytest.mark.slow
def test_a_run_with_no_save_map_writes_none(cpu, tmp_path):
    out = tmp_path / "run"
    assert main(["slam", *TINY, "--no-save-map", "--out", str(out)]) == 0
    assert not (out / "map").exists() and "saved_map" not in json.loads((out / "summary.json").read_text())
    assert (out / "map.ply").exists() and (out / "trajectory.tum").exists()


@pytest.mark.slow
def test_every_run_saves_its_map_and_save_map_puts_it_elsewhere(cpu, tmp_path, capsys):
    from ti_fusion.io.trajectory import read_tum
    from ti_fusion.slam.saved_map import load_map

    out = tmp_path / "run"
    assert main(["slam", *TINY, "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    saved = load_map(out)
    assert saved.count == summary["surfels"] == summary["saved_map"]["surfels"] > 0
    assert summary["saved_map"]["folder"] == str(out / "map")
    assert summary["saved_map"]["bytes"] == sum((out / "map" / n).stat().st_size for n in (HEADER, DATA))
    assert saved.intrinsics.width == 160 and saved.last_frame == 3 and saved.frames_fused == 4
    capsys.readouterr()
    assert main(["inspect", str(out)]) == 0  # the run's log, then its saved map
    report = capsys.readouterr().out
    assert report.index("log: ") < report.index(f"saved map: {out / 'map'}") and f"surfels   {saved.count:,}" in report

    elsewhere = tmp_path / "maps" / "room"
    other = tmp_path / "run2"
    assert main(["slam", *TINY, "--out", str(other), "--save-map", str(elsewhere)]) == 0
    assert not (other / "map").exists()
    # the same run: the same map, and saving it changed no pose
    assert (elsewhere / DATA).read_bytes() == (out / "map" / DATA).read_bytes()
    assert (other / "trajectory.tum").read_bytes() == (out / "trajectory.tum").read_bytes()
    assert len(read_tum(other / "trajectory.tum")[0]) == 4
    # a folder holding a saved map is replaced; one holding anything else is refused before the first frame
    assert main(["slam", *TINY, "--out", str(tmp_path / "run3"), "--save-map", str(elsewhere)]) == 0
    (elsewhere / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert main(["slam", *TINY, "--out", str(tmp_path / "run4"), "--save-map", str(elsewhere)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"ti-fusion slam: error: {elsewhere}: --save-map: holds notes.txt, not a saved map: give a new "
                   "folder or one holding only a saved map")
    assert not (tmp_path / "run4" / "trajectory.tum").exists()


@pytest.mark.slow
def test_saving_changes_no_pose(cpu, tmp_path):
    """The same frames with and without the saved map: the same trajectory.tum, byte for byte."""
    from ti_fusion.io.datasets import open_dataset
    from ti_fusion.io.outputs import RunDir
    from ti_fusion.slam.pipeline import SLAMPipeline

    trajectories = []
    for i, outputs in enumerate(({"saved_map": False}, {})):
        cfg = Config()
        cfg.dataset.downsample, cfg.dataset.stop, cfg.log.progress = 4, 6, False
        out = tmp_path / f"run{i}"
        SLAMPipeline(open_dataset(cfg.dataset, cfg.synth), cfg, RunDir("slam", out), None, show_progress=False,
                     outputs=outputs).run()
        assert (out / "map").exists() == (i == 1)
        trajectories.append((out / "trajectory.tum").read_bytes())
    assert trajectories[0] == trajectories[1]
