"""The engine's parameters: defaults from the schema, validation naming the field."""

import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.ndem.params import NAMES, Parameters


def test_defaults_are_the_schemas_and_the_engine_knobs_its_own():
    cfg = load_config(None)
    p = Parameters()
    for key in ("dt", "iterations", "method", "relaxation", "tolerance", "damping_steps"):
        assert getattr(p, key) == cfg["solver"][key]
    for key in ("density", "youngs_modulus", "poisson_ratio", "friction", "wall_friction"):
        assert getattr(p, key) == cfg["material"][key]
    np.testing.assert_array_equal(p.gravity, cfg["solver"]["gravity"])
    assert (p.contact_margin, p.slabs, p.warm_start) == (0.02, 16, True)
    assert NAMES[0] == "dt" and "warm_start" in NAMES


def test_from_config_takes_the_given_fields_and_converts_types():
    p = Parameters.from_config({"solver": {"dt": 0.002, "iterations": 7.0}, "material": {}})
    assert p.dt == 0.002 and p.iterations == 7 and isinstance(p.iterations, int)
    assert p.friction == Parameters().friction
    q = p.with_(gravity=[0, 0, -1.62], warm_start=0)
    assert q.gravity.dtype == np.float64 and q.gravity[2] == -1.62 and q.warm_start is False
    assert p.gravity[2] != -1.62  # with_ copies


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"dt": float("nan")}, "dt must be > 0 s"),
        ({"iterations": 2.5}, "iterations must be an integer >= 1"),
        ({"method": "jacobi"}, "method must be one of pgs, nncg, got 'jacobi'"),
        ({"relaxation": 2.0}, r"relaxation must be in \(0, 2\)"),
        ({"max_overlap": 0.0}, "max_overlap must be > 0"),
        ({"density": -1.0}, "density must be > 0 kg/m³"),
        ({"slabs": 0}, "slabs must be >= 1"),
        ({"wake_load": 0.5}, "wake_load must be >= 1, got 0.5"),
        ({"sleeper_compliance": 0.9}, "sleeper_compliance must be >= 1, got 0.9"),
        ({"tolerance": -1e-3}, "tolerance must be a finite number >= 0"),
        ({"wall_friction": float("inf")}, "wall_friction must be a finite number >= 0"),
        ({"gravity": [0.0, np.nan, -9.81]}, "gravity must be 3 finite numbers"),
    ],
)
def test_bad_values_are_refused_by_name(change, message):
    with pytest.raises(ValueError, match=message):
        Parameters().with_(**change)
