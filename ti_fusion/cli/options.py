"""The dataset options of the commands that read frames, made from the config fields marked ``Flag``.

A field of ``DatasetConfig`` or ``SynthConfig`` whose annotation holds ``Flag`` is the option ``--name``
(hyphens for underscores): its type and choices come from the field's rule, its help from the field's
comment in ti_fusion/config.py (the meaning docs/CONFIG.md gives it), and a value given is checked by the
rule and set on the config, after the config file and ``--set``. So a new option is one field.
"""

from __future__ import annotations

import argparse

from ti_fusion.config import Config, DatasetConfig, MapConfig, Rule, SynthConfig, field_docs, rules
from ti_fusion.errors import InputError

# The sections whose flags the commands that read frames take; the synthetic sequence's only without DATA; a flag
# with ``commands`` only on those.
SECTIONS = {"dataset": DatasetConfig, "synth": SynthConfig, "map": MapConfig}


def flags(section: str, command: str | None = None) -> list[tuple[str, Rule]]:
    """(field name, rule) of every field of ``section`` that is a command-line option (of ``command``, where
    given), in the class's order."""
    return [(name, rule) for name, rule in rules(SECTIONS[section]).items() if rule.flag is not None and
            (command is None or rule.flag.commands is None or command in rule.flag.commands)]


def option(name: str) -> str:
    return "--" + name.replace("_", "-")


def add_flags(group: argparse._ArgumentGroup, command: str | None = None, help_texts: bool = True) -> None:
    """Every section's flags (``command``'s) as options of ``group``; an option left out stays None (the
    config's value). Without ``help_texts`` the options have no help (a command line that does not ask for
    --help prints none, and the texts come from reading config.py's comments: ``field_docs``)."""
    docs = field_docs() if help_texts else None
    for section, section_type in SECTIONS.items():
        for name, rule in flags(section, command):
            help_text = None
            if docs is not None:
                help_text = docs[section_type.__name__, name]
                if section == "synth":
                    help_text = "without DATA: " + help_text
                help_text = f"{help_text} ({section}.{name})".replace("%", "%%")
            kwargs = dict(default=None, dest=name, metavar=rule.flag.metavar, help=help_text)
            if rule.kind is bool:  # a switch: given, it is true
                kwargs.pop("metavar")
                kwargs["action"] = "store_true"
            elif rule.choices is not None:
                kwargs["choices"] = rule.choices.choices
            elif rule.kind in (int, float):
                kwargs["type"] = rule.kind
            group.add_argument(option(name), **kwargs)


def apply_flags(args: argparse.Namespace, config: Config) -> None:
    """The flags given in ``args`` set on ``config``: each checked by its field's rule (one line naming the
    option otherwise); the synthetic sequence's refused with a dataset."""
    for section in SECTIONS:
        values = getattr(config, section)
        for name, rule in flags(section):
            value = getattr(args, name, None)
            if value is None:
                continue
            narrower = rule.flag.range
            try:
                value = rule.check(value)
                if narrower is not None and not narrower.allows(value):
                    raise ValueError
            except ValueError:
                shown = f"{value:g}" if isinstance(value, float) else value
                raise InputError(None, f"{option(name)} {shown}: must be {_allowed(rule)}") from None
            if section == "synth" and config.dataset.path:
                raise InputError(None, f"{option(name)} is for the synthetic sequence (no DATA); "
                                       f"{config.dataset.path} is recorded data")
            setattr(values, name, value)


def _allowed(rule: Rule) -> str:
    """What an option takes, as its error line says it: "at least 1" for a count, "a positive number"."""
    r = rule.flag.range or rule.range
    if r is not None and rule.kind in (int, float):
        bounds = (r.ge, r.gt, r.le, r.lt)
        if bounds == (None, 0, None, None):
            return f"a positive {'integer' if rule.kind is int else 'number'}"
        if rule.kind is int and r.ge is not None and bounds[1:] == (None, None, None):
            return f"at least {r.ge}"
        return f"{_KIND_WORDS[rule.kind]} {r}"
    return rule.describe()


_KIND_WORDS = {int: "an integer", float: "a number"}
