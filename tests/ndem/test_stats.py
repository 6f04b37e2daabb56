"""A step's summary and the divergence error."""

import dataclasses

import pytest

from dozerlab.ndem.stats import DivergenceError, StepStats
from dozerlab.runtime import DozerlabError


def test_divergence_is_a_dozerlab_and_a_runtime_error():
    err = DivergenceError("overlap too large")
    assert isinstance(err, DozerlabError) and isinstance(err, RuntimeError)


def test_step_stats_are_frozen_and_count_no_sweeps_unless_told():
    s = StepStats(3, 0.03, 10, 2, 1e-6, 1e-4, 0.002)
    assert s.iterations == 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.contacts = 11
