import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.scenarios.bed import Bed

LENGTH, WIDTH, RADIUS = 4.0, 1.2, 0.05


def lattice_bed(scenario: str, profile, seed: int = 0) -> Bed:
    """A bed of equal spheres stacked in columns up to ``profile(x)`` (no physics; fast)."""
    rng = np.random.default_rng(seed)
    points = []
    for x in np.arange(RADIUS, LENGTH, 2 * RADIUS):
        for y in np.arange(-WIDTH / 2 + RADIUS, WIDTH / 2, 2 * RADIUS):
            for z in np.arange(RADIUS, max(profile(x) - RADIUS, RADIUS) + 1e-9, 2 * RADIUS):
                points.append((x + rng.uniform(-0.2, 0.2) * RADIUS, y, z))
    pos = np.array(points)
    n = len(pos)
    radii = np.full(n, RADIUS)
    masses = 2600.0 * 4.0 / 3.0 * np.pi * radii**3
    return Bed(
        scenario,
        LENGTH,
        WIDTH,
        pos,
        radii,
        masses,
        np.zeros((n, 3)),
        np.zeros((n, 3)),
        {"density": 2600.0},
        seed,
    )


@pytest.fixture(scope="session")
def config():
    return load_config()


@pytest.fixture(scope="session")
def hill_bed():
    return lattice_bed(
        "hill", lambda x: 0.2 + 0.5 * np.cos(np.clip((x - 2.2) / 0.8, -1, 1) * np.pi / 2) ** 2
    )


@pytest.fixture(scope="session")
def step_bed():
    return lattice_bed("step", lambda x: 0.6 if x < 2.0 else 0.15)


@pytest.fixture(autouse=True)
def _no_mlflow(monkeypatch):
    monkeypatch.setenv("DOZERLAB_MLFLOW", "0")
