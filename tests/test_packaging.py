"""The package's declared dependencies: pyproject.toml is their one list, and it covers every
third-party module the package imports."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _name(requirement: str) -> str:
    """The normalised distribution name of a requirement string (PEP 503)."""
    name = re.match(r"[A-Za-z0-9._-]+", requirement.strip())
    assert name is not None, requirement
    return re.sub(r"[-_.]+", "-", name.group(0)).lower()


def _imported_top_level(src: Path) -> set[str]:
    """Top-level names of the absolute imports in every module under ``src``."""
    names = set()
    for path in src.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return names


def test_requirements_txt_installs_the_project_and_lists_nothing_of_its_own():
    lines = [
        line.strip()
        for line in (ROOT / "requirements.txt").read_text().splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    assert lines == [f"-e .[{','.join(extras)}]"]


def test_every_third_party_import_of_the_package_is_a_declared_dependency():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    declared = {_name(r) for r in project["dependencies"]}
    distributions = packages_distributions()
    third_party = _imported_top_level(ROOT / "src" / "dozerlab") - set(sys.stdlib_module_names)
    third_party -= {"dozerlab"}
    assert third_party, "no third-party imports found: the scan is broken"
    dists = {module: distributions.get(module, [module]) for module in sorted(third_party)}
    missing = {m: d for m, d in dists.items() if not declared & {_name(x) for x in d}}
    assert not missing, f"imported but not in pyproject.toml's dependencies: {missing}"
