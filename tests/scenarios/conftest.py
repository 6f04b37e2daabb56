import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.scenarios.bed import Bed
from tests import helpers

LENGTH, WIDTH, RADIUS = 4.0, 1.2, 0.05


def _bed(scenario: str, profile, seed: int = 0) -> Bed:
    """A jittered lattice bed of the scenarios tests' size (see :func:`tests.helpers.lattice_bed`)."""
    return helpers.lattice_bed(
        scenario, profile, length=LENGTH, width=WIDTH, radius=RADIUS, seed=seed, jitter=0.2
    )


@pytest.fixture(scope="session")
def config():
    return load_config()


@pytest.fixture(scope="session")
def hill_bed():
    return _bed(
        "hill", lambda x: 0.2 + 0.5 * np.cos(np.clip((x - 2.2) / 0.8, -1, 1) * np.pi / 2) ** 2
    )


@pytest.fixture(scope="session")
def step_bed():
    return _bed("step", lambda x: 0.6 if x < 2.0 else 0.15)


@pytest.fixture(autouse=True)
def _no_mlflow(monkeypatch):
    monkeypatch.setenv("DOZERLAB_MLFLOW", "0")
