"""The benchmark scripts import only names the package has: they are run by hand, rarely, and a
package refactor must not break them unseen."""

from __future__ import annotations

import ast
import importlib
import importlib.util
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted((ROOT / "benchmarks").glob("*.py"))


def _missing(script: Path) -> list[str]:
    missing = []
    for node in ast.walk(ast.parse(script.read_text())):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("dozerlab"):
            module = importlib.import_module(str(node.module))
            for alias in node.names:
                if not hasattr(module, alias.name):
                    try:
                        importlib.import_module(f"{node.module}.{alias.name}")
                    except ModuleNotFoundError:
                        missing.append(f"{node.module}.{alias.name}")
    return missing


def test_there_are_benchmarks():
    assert len(SCRIPTS) >= 5


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_benchmark_imports_exist(script):
    assert _missing(script) == []


def test_ndem_against_lammps_measures_overlaps_with_the_blade_box():
    # both engines' overlaps are read by this one function, the blade's box included
    spec = importlib.util.spec_from_file_location("nvl", ROOT / "benchmarks" / "ndem_vs_lammps.py")
    assert spec and spec.loader
    nvl = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(nvl)
    r = np.full(2, 0.02)
    x = np.array([[1.0, 0.0, 0.5], [2.0, 0.0, 0.5]])  # apart, clear of the ground and walls
    box = (4.0, 1.0)
    assert nvl.overlap_fraction(x, r, box) == 0.0
    blade = (np.array([0.89, -0.3, 0.0]), np.array([0.99, 0.3, 1.0]))  # 1 cm behind the first
    assert nvl.overlap_fraction(x, r, box, blade) == pytest.approx(0.5)
    inside = (blade[0] + [0.05, 0.0, 0.0], blade[1] + [0.05, 0.0, 0.0])
    assert nvl.overlap_fraction(x, r, box, inside) == pytest.approx(1.0)


def test_zone_departure_tells_a_wider_spread_from_a_bias():
    # NDEM's draws: one mean push curve and its chaos; the designs: the same chaos, a wider one,
    # and the same chaos about a push 3 % larger
    spec = importlib.util.spec_from_file_location(
        "naz", ROOT / "benchmarks" / "ndem_active_zone.py"
    )
    assert spec and spec.loader
    naz = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(naz)
    rng = np.random.default_rng(0)
    t = np.arange(4000) * 0.01
    curve = -2000.0 - 300.0 * np.sin(t)

    def runs(n: int, scale: float, noise: float) -> list[dict]:
        out = []
        for _ in range(n):
            f = np.zeros((t.size, 3))
            f[:, 0] = scale * curve + noise * rng.standard_normal(t.size)
            out.append({"force": f, "row_dt": 0.01})
        return out

    ndem = runs(8, 1.0, 400.0)
    same = naz.departure(ndem, runs(8, 1.0, 400.0))
    wider = naz.departure(ndem, runs(8, 1.0, 600.0))
    harder = naz.departure(ndem, runs(8, 1.03, 400.0))
    assert same["spread_ratio"] == pytest.approx(1.0, abs=0.05)
    assert same["apart_over_chaos"] == pytest.approx(1.0, abs=0.1)
    assert wider["spread_ratio"] == pytest.approx(1.5, abs=0.07)
    assert wider["apart_over_chaos"] == pytest.approx(1.0, abs=0.1)
    # a bias as large as what chaos alone leaves between the means: about √2 of it
    assert harder["apart_over_chaos"] == pytest.approx(np.sqrt(2.0), abs=0.12)
    assert harder["push_difference_n"] == pytest.approx(60.0, abs=5.0)
    assert harder["push_difference_se"] > 5.0 and abs(same["push_difference_se"]) < 3.0
    # low-passed over 0.1 s (10 rows), a run's noise of 400 N falls to about 400/√10 N
    assert same["spread_ndem"] == pytest.approx(400.0 / np.sqrt(10) / 2000.0, rel=0.15)
