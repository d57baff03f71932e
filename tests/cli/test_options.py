"""The dataset options made from the config fields marked Flag: names, help, values checked and set."""

from __future__ import annotations

import pytest

from ti_fusion.cli.main import _apply_dataset_args, build_parser
from ti_fusion.cli.options import SECTIONS, flags, option
from ti_fusion.config import field_docs, load_config
from ti_fusion.errors import InputError

# The options users know: they keep these names.
KNOWN = ("--format", "--depth-scale", "--intrinsics", "--ground-truth", "--depth-topic", "--color-topic",
         "--camera-info-topic", "--gt-topic", "--camera", "--color-extrinsics", "--color-intrinsics", "--downsample",
         "--start", "--stop", "--stride", "--scene", "--trajectory")


def _actions(command: str) -> dict:
    parser, _ = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices[command]
    return {s: a for a in sub._actions for s in a.option_strings}


@pytest.mark.parametrize("command", ["slam", "vo", "fuse", "icp"])
def test_every_flagged_field_is_an_option_with_its_comment_as_help(command):
    actions = _actions(command)
    docs = field_docs()
    assert set(KNOWN) | {"--frames"} <= set(actions)
    for section, section_type in SECTIONS.items():
        for name, rule in flags(section):
            if rule.flag.commands is not None and command not in rule.flag.commands:
                assert option(name) not in actions  # an option of other commands only (--save-map: slam's)
                continue
            action = actions[option(name)]
            assert docs[section_type.__name__, name] in action.help and f"({section}.{name})" in action.help
            assert action.default is None  # left out: the config's value stands
            if rule.choices is not None:
                assert tuple(action.choices) == rule.choices.choices


def test_a_command_line_without_help_builds_the_options_without_their_texts(capsys):
    """The help texts come from reading config.py's comments (``field_docs``): a command line that cannot ask for
    --help gets the same options without them; one that can (an abbreviation of --help too) gets them."""
    from ti_fusion.cli.main import _asks_for_help, main

    parser, _ = build_parser("slam", help_texts=False)
    sub = next(a for a in parser._actions if a.dest == "command").choices["slam"]
    bare = {s: a for a in sub._actions for s in a.option_strings}
    full = _actions("slam")
    assert set(bare) == set(full) and all(bare[o].help is None for o in KNOWN)
    assert [bare[o].dest for o in KNOWN] == [full[o].dest for o in KNOWN]
    assert not _asks_for_help(["slam", "../data", "--frames", "3", "--out", "run"])
    assert all(_asks_for_help(["slam", flag]) for flag in ("-h", "--help", "--he", "-vh"))
    with pytest.raises(SystemExit):
        main(["slam", "--hel"])
    assert "(dataset.depth_scale)" in capsys.readouterr().out


def _apply(argv: list[str], overrides: list[str] | None = None):
    parser, _ = build_parser()
    args = parser.parse_args(["slam", *argv])
    config = load_config(None, overrides)
    _apply_dataset_args(args, config)
    return config


def test_an_option_sets_its_field_after_set_and_its_rule_checks_it():
    config = _apply(["DATA", "--stride", "2", "--depth-scale", "1000", "--color-topic", "none", "--format", "tum"],
                    ["dataset.stride=3", "dataset.depth_scale=5000"])
    ds = config.dataset
    assert (ds.path, ds.stride, ds.depth_scale, ds.color_topic, ds.format) == ("DATA", 2, 1000.0, "none", "tum")
    assert _apply(["--scene", "wall", "--frames", "5"]).synth.scene == "wall"
    with pytest.raises(InputError, match=r"^--depth-scale 0: must be a positive number$"):  # 0 = unset: no option
        _apply(["--depth-scale", "0"])
    with pytest.raises(InputError, match=r"^--stop 0: must be at least 1$"):
        _apply(["--stop", "0"])
    with pytest.raises(InputError, match=r"^--trajectory is for the synthetic sequence \(no DATA\); DATA is recorded"):
        _apply(["DATA", "--trajectory", "poses.tum"])
