"""The process's age (``ti_fusion.timing.process_age_s``): from the kernel's record of its start, or from the exec
of a script that set up the environment first (scripts/run.sh says when, in ``TI_FUSION_EXEC_AT``)."""

import time

import pytest

from ti_fusion import timing


def test_the_age_counts_from_a_scripts_exec_where_it_says_so(monkeypatch):
    monkeypatch.setattr(timing, "_EXEC_AT", None)
    age = timing.process_age_s()
    if age is None:
        pytest.skip("no /proc here")
    monkeypatch.setattr(timing, "_EXEC_AT", repr(time.time()))  # exec'd just now: the set-up before is not counted
    assert timing.process_age_s() < age
    for said in ("not a time", repr(time.time() + 3600), repr(time.time() - age - 3600)):
        monkeypatch.setattr(timing, "_EXEC_AT", said)  # garbage, after now, before the process: the kernel's record
        assert timing.process_age_s() >= age


def test_the_scripts_time_is_read_once_and_not_handed_on():
    import os

    assert "TI_FUSION_EXEC_AT" not in os.environ  # a process started from this one counts from its own start
