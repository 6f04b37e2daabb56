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
