"""The typed config: sections, overrides, and settings that were removed."""

import pytest

from ti_fusion.config import REMOVED, Config, load_config
from ti_fusion.errors import InputError


def test_pyramid_section_and_removed_keys(tmp_path):
    cfg = load_config(None, ["pyramid.depth_smooth_radius=3", "pyramid.normal_max_depth_jump=0.07"])
    assert cfg.pyramid.depth_smooth_radius == 3 and cfg.pyramid.normal_max_depth_jump == 0.07
    assert "pyramid" in Config().to_dict()
    # the frame-map settings used to be in [icp]: the old name is one line saying where it went
    path = tmp_path / "old.toml"
    path.write_text("[icp]\ndepth_smooth_radius = 2\ndist_threshold = 0.05\n")
    with pytest.raises(InputError, match=r"icp.depth_smooth_radius was removed: moved to pyramid.depth_smooth_radius$"):
        load_config(path)


@pytest.mark.parametrize("given", [["maps.depth_smooth_radius=3"], "[maps]\ndepth_smooth_radius = 3\n"])
def test_the_renamed_maps_section_is_one_line_naming_the_new_one(tmp_path, given):
    """[maps] became [pyramid] ('map' is the surfel map): an old file or --set says so in one line."""
    path = None
    if isinstance(given, str):
        path = tmp_path / "old.toml"
        path.write_text(given)
    with pytest.raises(InputError, match=r"section 'maps' was renamed: it is \[pyramid\]") as info:
        load_config(path, [] if path else given)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("key", sorted(f"{s}.{k}" for s, k in REMOVED))
def test_a_removed_setting_is_one_line_naming_it(key):
    with pytest.raises(InputError, match=rf"^--set: {key} was removed: \S") as info:
        load_config(None, [f"{key}=1"])
    assert "\n" not in str(info.value)
    section, name = key.split(".")
    assert name not in Config().to_dict()[section]


def test_unknown_setting_is_one_clear_line():
    with pytest.raises(InputError, match="unknown setting 'depth_smooth'"):
        load_config(None, ["pyramid.depth_smooth=2"])


def test_non_positive_range_check_is_refused(cpu):
    from ti_fusion.config import PyramidConfig
    from ti_fusion.kernels.pyramid import FramePyramid

    with pytest.raises(InputError, match="pyramid.depth_sigma"):
        FramePyramid(PyramidConfig(depth_sigma=0.0), 8, 8, levels=1)


# --------------------------------------------------------------------------------------------------
# Every value is checked against its field's rule when the config is built
# --------------------------------------------------------------------------------------------------
def test_every_field_of_every_section_has_a_rule():
    """A field added without a rule (a Range, OneOf, Text or Length in its annotation) fails here."""
    import dataclasses

    from ti_fusion.config import rules

    for section in dataclasses.fields(Config):
        section_type = type(getattr(Config(), section.name))
        assert set(rules(section_type)) == {f.name for f in dataclasses.fields(section_type)}, section.name


def test_a_field_without_a_rule_is_caught():
    from dataclasses import dataclass
    from typing import Annotated

    from ti_fusion.config import Range, rules

    @dataclass
    class Section:
        checked: Annotated[int, Range(ge=0)] = 1
        flag: bool = True          # a bool is true or false: no more rule needed
        unchecked: int = 3         # a number without a range
        words: str = ""            # text without choices or Text()

    with pytest.raises(TypeError, match="Section: no rule for unchecked, words"):
        rules(Section)


def test_the_defaults_follow_their_rules():
    from ti_fusion.config import check_config

    assert check_config(Config()) == Config()


@pytest.mark.parametrize("override, line", [
    ("icp.dist_threshold=-0.1", "--set: icp.dist_threshold = -0.1: must be a number > 0"),
    ("fusion.dist_threshold=-0.03", "--set: fusion.dist_threshold = -0.03: must be a number > 0"),
    ("icp.depth_weighting=maybe", "--set: icp.depth_weighting = 'maybe': must be true or false"),
    ("icp.min_inliers=2.7", "--set: icp.min_inliers = 2.7: must be an integer >= 6"),
    ("slam.relocalise=featurs", "--set: slam.relocalise = 'featurs': must be one of features, none"),
    ("icp.robust=hubber", "--set: icp.robust = 'hubber': must be one of none, huber, tukey"),
    ("icp.iterations=[]", "--set: icp.iterations = []: must be a list of integers >= 0 (at least 1)"),
    ("icp.iterations=5", "--set: icp.iterations = 5: must be a list of integers >= 0 (at least 1)"),
    ("icp.iterations=[10,-1]", "--set: icp.iterations = [10, -1]: must be a list of integers >= 0 (at least 1)"),
    ("slam.min_inlier_ratio=1.5", "--set: slam.min_inlier_ratio = 1.5: must be a number in [0, 1]"),
    ("dataset.stop=0", "--set: dataset.stop = 0: must be an integer >= 1, or None"),
    ("fusion.level=-2", "--set: fusion.level = -2: must be an integer >= -1"),
    ("log.map_every=True", "--set: log.map_every = True: must be an integer >= 0"),
    ("vo.voxel_size=nan", "--set: vo.voxel_size = 'nan': must be a number > 0"),
    ("dataset.format=icl", "--set: dataset.format = 'icl': must be one of auto, tum, iclnuim, 7scenes"),
])
def test_a_value_against_its_rule_is_one_line_naming_key_value_and_rule(override, line):
    with pytest.raises(InputError) as info:
        load_config(None, [override])
    message = str(info.value)
    assert message.startswith(line) and "\n" not in message


def test_values_are_read_as_their_field_type():
    cfg = load_config(None, ["icp.depth_weighting=no", "fusion.grow=1", "icp.iterations=(3, 2.0)",
                             "fusion.capacity=1e6", "dataset.stop=None", "icp.dist_threshold=1",
                             "dataset.path=2023", "dataset.intrinsics_file=1,2"])
    assert cfg.icp.depth_weighting is False and cfg.fusion.grow is True
    assert cfg.icp.iterations == [3, 2] and all(type(n) is int for n in cfg.icp.iterations)
    assert cfg.fusion.capacity == 1_000_000 and type(cfg.fusion.capacity) is int
    assert cfg.dataset.stop is None
    assert cfg.icp.dist_threshold == 1.0 and type(cfg.icp.dist_threshold) is float
    assert cfg.dataset.path == "2023"  # a text field takes the text as written
    assert cfg.dataset.intrinsics_file == "1,2"


def test_a_file_value_against_its_rule_names_the_file(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text("[icp]\ndist_threshold = 0.05\nrobust = \"hubber\"\n")
    with pytest.raises(InputError, match=r"run\.toml: icp\.robust = 'hubber': must be one of none, huber, tukey"):
        load_config(path)
    # YAML reads 1e-4 (no dot) as text: a number written as text is still that number
    path = tmp_path / "run.json"
    path.write_text('{"icp": {"stop_update": "1e-4", "iterations": [4, 2]}, "slam": {"motion_model": false}}')
    cfg = load_config(path)
    assert cfg.icp.stop_update == 1e-4 and cfg.icp.iterations == [4, 2] and cfg.slam.motion_model is False


def test_choices_match_the_code_that_uses_them():
    from ti_fusion.config import rules, ICPConfig
    from ti_fusion.io.datasets import FORMATS
    from ti_fusion.tracking.terms.point_to_plane import ROBUST_CODES
    from ti_fusion.config import DatasetConfig

    icp = rules(ICPConfig)
    assert set(icp["robust"].choices.choices) == set(ROBUST_CODES)
    assert rules(DatasetConfig)["format"].choices.choices == ("auto", *FORMATS)


# --------------------------------------------------------------------------------------------------
# Any file content is one line at the command line (not UTF-8, unparseable, a list, a value for a section)
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, content, line", [
    ("list.yaml", b"- 1\n", "config's top level is a list: expected a table of sections (e.g. icp: with its "
                            "settings)"),
    ("list.json", b"[1, 2]", "config's top level is a list: expected a table of sections (e.g. icp: with its "
                             "settings)"),
    ("latin1.yaml", "icp:\n  robust: 'huber' # é\n".encode("latin-1"),
     "config is not UTF-8 text (line 2, byte b'\\xe9'): save it as UTF-8"),
    ("broken.yaml", b"icp: [\n  a: b\n", "cannot parse config: line 3, column 1: expected ',' or ']', but got "
                                         "'<stream end>'"),
    ("scalar.toml", b"icp = 5\n", "section 'icp' must be a table of settings (e.g. [icp] in TOML), not a number (5)"),
])
def test_any_config_file_content_is_one_line(tmp_path, capsys, name, content, line):
    from ti_fusion.cli.main import main

    path = tmp_path / name
    path.write_bytes(content)
    assert main(["vo", "--config", str(path), "--out", str(tmp_path / "run"), "--quiet"]) == 2
    assert capsys.readouterr().err.splitlines() == [f"ti-fusion vo: error: {path}: {line}"]


def test_relative_paths_in_a_config_file_are_relative_to_the_file(tmp_path, monkeypatch):
    folder = tmp_path / "configs"
    folder.mkdir()
    (folder / "cam.txt").write_text("525 525 319.5 239.5\n")
    path = folder / "run.toml"
    path.write_text('[dataset]\npath = "../data/seq"\nintrinsics = "cam.txt"\nground_truth = "/abs/gt.txt"\n'
                    '[synth]\ntrajectory = "poses.tum"\n')
    monkeypatch.chdir(tmp_path)
    cfg = load_config(path)
    assert cfg.dataset.path == str(folder / "../data/seq")
    assert cfg.dataset.intrinsics == str(folder / "cam.txt") and cfg.dataset.ground_truth == "/abs/gt.txt"
    assert cfg.synth.trajectory == str(folder / "poses.tum")
    path.write_text('[dataset]\nintrinsics = "525,525,319.5,239.5"\n')  # numbers, not a file
    assert load_config(path).dataset.intrinsics == "525,525,319.5,239.5"
    # --set paths stay the working directory's
    assert load_config(path, ["dataset.path=seq"]).dataset.path == "seq"


# --------------------------------------------------------------------------------------------------
# docs/CONFIG.md: every key, generated from this module, main settings and advanced ones apart
# --------------------------------------------------------------------------------------------------
def test_docs_config_is_what_config_py_gives(script):
    """A key added, removed or changed without ``python scripts/config_doc.py`` fails here."""
    assert script("config_doc").main(["--check"]) == 0, "docs/CONFIG.md is out of date: python scripts/config_doc.py"


def test_every_key_has_a_meaning_and_the_advanced_list_names_real_keys():
    import dataclasses

    from ti_fusion import config as config_module
    from ti_fusion.config import ADVANCED

    comments = config_module.field_docs()
    sections = {f.name: type(getattr(Config(), f.name)) for f in dataclasses.fields(Config)}
    for name, section_type in sections.items():
        for f in dataclasses.fields(section_type):
            assert comments.get((section_type.__name__, f.name)), f"{name}.{f.name} has no comment in config.py"
    for name, keys in ADVANCED.items():
        assert set(keys) <= {f.name for f in dataclasses.fields(sections[name])}, name
    for section, key in REMOVED:
        assert key not in {f.name for f in dataclasses.fields(sections[section])}, (section, key)


def test_a_yaml_alias_bomb_is_refused_without_expanding_it(tmp_path):
    """A few hundred bytes of YAML aliases expand into 9**9 values: refused by counting (which stops at the
    bound), never walked or printed in full."""
    lines = ['a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for prev, name in zip("abcdefg", "bcdefgh"):
        lines.append(f"{name}: &{name} [{', '.join([f'*{prev}'] * 9)}]")
    lines.append(f"icp: {{iterations: [{', '.join(['*h'] * 9)}]}}")
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    assert path.stat().st_size < 500
    with pytest.raises(InputError, match=r"bomb.yaml: config holds more than 100000 values \(YAML aliases"):
        load_config(path)
    from ti_fusion.config import _show

    assert len(_show(list(range(10_000)))) < 210
