"""Fixtures of the skeleton tests."""
from __future__ import annotations

import pytest

OLD_TRIM_PERIODS = 1.5   # skeleton.pipeline.TRIM_PERIODS before stop 37 (now 0.25)
OLD_FIT_TRIM = False     # skeleton.pipeline.FIT_TRIM before stop 37 (now True)


@pytest.fixture
def old_trim(monkeypatch):
    """The low-pass that a guard test's failure state was found with: 1.5 periods of the
    cut-off cut from every run end (``skeleton.pipeline.TRIM_PERIODS``), and the joint and
    star fits on the untrimmed low-pass (``FIT_TRIM``). With stop 37's low-pass the data
    those tests build differ, and several failure states no longer arise (the premises,
    ``assert not ...`` with the guarded rule off, fail); the rule each test guards is still
    what resolves that state."""
    from skeleton import pipeline

    monkeypatch.setattr(pipeline, "TRIM_PERIODS", OLD_TRIM_PERIODS)
    monkeypatch.setattr(pipeline, "FIT_TRIM", OLD_FIT_TRIM)
    return OLD_TRIM_PERIODS, OLD_FIT_TRIM
