"""Terrain: each scenario's target ground height h(x, y) in m, from the config (docs/physics.md#beds).

A scenario under the config's ``scenarios`` is one of

- a built-in preset, named by its key (``hill``, ``step``, ``trench``): a parametric profile
  along x;
- ``kind: profile``: ``points: [[x, z], …]``, the height z (m) at x (m) from the bed's start,
  linear between points, the first and last height held beyond them, constant across the width;
- ``kind: heightmap``: ``file: PATH``, a 2-D array of heights (m), ``.npy`` or ``.csv``: row i is
  x = i·length/(rows − 1) and column j is y = −width/2 + j·width/(columns − 1) (the samples span
  the ground rectangle corner to corner; a single row or column is held constant along its
  axis), bilinear between samples. A relative path is read from the working directory.

Every kind gives the same thing, :func:`target_height` on points of the ground, which the
emitter fills (``scenarios/build.py``). :func:`check_terrain` refuses what cannot be built,
naming the field: heights above the bed's box (the schema's bound on bed heights) or below a
grain (2 × ``bed.radius``), NaN or infinity, a file that is not a 2-D array of numbers or does
not exist, profile x not increasing or outside the bed.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.runtime import ConfigError

#: The built-in scenarios, each a named preset of the config's ``scenarios`` section.
PRESETS: tuple[str, ...] = ("hill", "step", "trench")
#: The kinds of scenario a config defines by its data.
KINDS: tuple[str, ...] = ("profile", "heightmap")
#: The field holding each preset's lowest bed level (m above the ground).
PRESET_LOWEST = {"hill": "base_height", "step": "low_height", "trench": "bottom_height"}


def kind_of(name: str, shape: Mapping[str, Any]) -> str:
    """The kind of the scenario ``name`` whose config section is ``shape``: its ``kind``, or the
    preset it names."""
    kind = shape.get("kind")
    if kind is not None:
        return str(kind)
    if name in PRESETS:
        return name
    raise ConfigError(
        f"config field 'scenarios.{name}.kind': a scenario that is not a preset "
        f"({', '.join(PRESETS)}) needs a kind (allowed: one of {list(KINDS)})"
    )


def shape_of(name: str, config: Mapping[str, Any]) -> Mapping[str, Any]:
    """Scenario ``name``'s section of the config's ``scenarios``; :class:`ConfigError` when the
    config does not define it."""
    if name not in config["scenarios"]:
        raise ConfigError(
            f"scenario '{name}' is not defined (allowed: one of {sorted(config['scenarios'])}, or a "
            "scenario added under the config's scenarios)"
        )
    return config["scenarios"][name]


@cache
def _read_heightmap(path: str, mtime_ns: int) -> np.ndarray:
    """The array of the heightmap at ``path`` as written at ``mtime_ns`` (cached per version)."""
    p = Path(path)
    if p.suffix.lower() == ".npy":
        arr = np.load(p, allow_pickle=False)
    else:
        arr = np.loadtxt(p, delimiter=",", dtype=np.float64, ndmin=2)
    return arr


def read_heightmap(name: str, file: str | Path) -> np.ndarray:
    """The heights (m) of scenario ``name``'s heightmap ``file`` (``.npy`` or ``.csv``), shape
    (x samples, y samples), float64. Raises :class:`ConfigError` naming ``scenarios.{name}.file``
    when it is missing, unreadable, not 2-D, not numbers or not finite."""
    field = f"scenarios.{name}.file"
    path = Path(file)
    if path.suffix.lower() not in (".npy", ".csv"):
        raise ConfigError(f"config field '{field}': {path} is not a .npy or .csv file")
    if not path.is_file():
        raise ConfigError(f"config field '{field}': heightmap file {path} does not exist")
    try:
        arr = _read_heightmap(str(path.resolve()), path.stat().st_mtime_ns)
    except (ValueError, OSError, EOFError) as exc:
        raise ConfigError(
            f"config field '{field}': {path} is not a 2-D array of numbers ({exc})"
        ) from None
    if arr.ndim != 2 or arr.size == 0 or not np.issubdtype(arr.dtype, np.number):
        raise ConfigError(
            f"config field '{field}': {path} is not a 2-D array of numbers: it holds a "
            f"{arr.ndim}-D array of {arr.dtype}, shape {arr.shape} (allowed: rows along x, "
            "columns along y)"
        )
    arr = arr.astype(np.float64)
    bad = np.argwhere(~np.isfinite(arr))
    if bad.size:
        raise ConfigError(
            f"config field '{field}': {path} holds {len(bad)} value(s) that are not finite, first "
            f"at row {bad[0][0]}, column {bad[0][1]} (allowed: finite heights in m)"
        )
    return arr


def _bilinear(
    z: np.ndarray, length: float, width: float, x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """Bilinear interpolation of samples ``z`` (nx, ny) spanning [0, length] × [−width/2, width/2]
    corner to corner, at ``x``, ``y`` (m, broadcast together), clamped to the rectangle."""
    nx, ny = z.shape
    u = np.clip(np.asarray(x, dtype=np.float64) / length, 0.0, 1.0) * (nx - 1)
    v = np.clip(np.asarray(y, dtype=np.float64) / width + 0.5, 0.0, 1.0) * (ny - 1)
    u, v = np.broadcast_arrays(u, v)
    i0 = np.minimum(np.floor(u).astype(np.int64), max(nx - 2, 0))
    j0 = np.minimum(np.floor(v).astype(np.int64), max(ny - 2, 0))
    i1, j1 = np.minimum(i0 + 1, nx - 1), np.minimum(j0 + 1, ny - 1)
    fu, fv = u - i0, v - j0
    return (
        z[i0, j0] * (1 - fu) * (1 - fv)
        + z[i1, j0] * fu * (1 - fv)
        + z[i0, j1] * (1 - fu) * fv
        + z[i1, j1] * fu * fv
    )


def _preset(kind: str, s: Mapping[str, Any], length: float, x: np.ndarray) -> np.ndarray:
    """A preset's height (m) at ``x`` (m) along a bed of ``length`` (m)."""
    if kind == "step":
        return np.where(x < s["edge"] * length, float(s["high_height"]), float(s["low_height"]))
    u = np.clip((x - s["center"] * length) / (s["half_width"] * length), -1.0, 1.0)
    bump = np.cos(0.5 * np.pi * u) ** 2
    if kind == "hill":
        return s["base_height"] + (s["peak_height"] - s["base_height"]) * bump
    return s["base_height"] - (s["base_height"] - s["bottom_height"]) * bump


def target_height(
    name: str, config: Mapping[str, Any], x: np.ndarray, y: np.ndarray | float = 0.0
) -> np.ndarray:
    """Scenario ``name``'s target ground height (m) at ``x`` (m along the bed) and ``y`` (m
    across it, 0 on the centre line), broadcast together; ``config`` is a validated config."""
    bed = config["bed"]
    length, width = float(bed["length"]), float(bed["width"])
    s = shape_of(name, config)
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    kind = kind_of(name, s)
    if kind == "profile":
        px, pz = np.asarray(s["points"], dtype=np.float64).T
        h = np.interp(x, px, pz)
    elif kind == "heightmap":
        h = _bilinear(read_heightmap(name, s["file"]), length, width, x, y)
    else:
        h = _preset(kind, s, length, x)
    return np.broadcast_to(h, np.broadcast_shapes(x.shape, y.shape)).astype(np.float64)


def heightmap_file(name: str, config: Mapping[str, Any]) -> str | None:
    """The heightmap file of scenario ``name`` (as the config spells it), None for other kinds."""
    s = config["scenarios"].get(name, {})
    return str(s["file"]) if s.get("kind") == "heightmap" else None


def lowest_level(name: str, config: Mapping[str, Any]) -> tuple[str, float]:
    """The field that sets scenario ``name``'s lowest ground height and that height (m)."""
    s = shape_of(name, config)
    kind = kind_of(name, s)
    if kind == "profile":
        return f"scenarios.{name}.points", float(min(z for _, z in s["points"]))
    if kind == "heightmap":
        return f"scenarios.{name}.file", float(read_heightmap(name, s["file"]).min())
    field = PRESET_LOWEST[kind]
    return f"scenarios.{name}.{field}", float(s[field])


def check_terrain(name: str, config: Mapping[str, Any], top: float) -> None:
    """Refuse scenario ``name`` of a validated config unless its bed can be built: a preset's
    heights in the wrong order; a profile or heightmap of heights above the bed's box (``top``,
    m: :func:`dozerlab.config.height_bound`) or below a grain, a profile's x not strictly increasing or outside [0, ``bed.length``], a heightmap file
    missing or not a 2-D array of finite numbers. Raises :class:`ConfigError` naming the field."""
    s = shape_of(name, config)
    kind = kind_of(name, s)
    if kind in PRESETS:
        high, low = {
            "hill": ("peak_height", "base_height"),
            "step": ("high_height", "low_height"),
            "trench": ("base_height", "bottom_height"),
        }[kind]
        if s[high] <= s[low]:
            raise ConfigError(
                f"config field 'scenarios.{name}.{high}': {s[high]} m must be > {low} ({s[low]} m)"
            )
        return
    needs, other = ("points", "file") if kind == "profile" else ("file", "points")
    if needs not in s:
        raise ConfigError(f"config field 'scenarios.{name}.{needs}': a {kind} needs it (required)")
    if other in s:
        raise ConfigError(
            f"config field 'scenarios.{name}.{other}': a {kind} takes {needs}, not {other}"
        )
    length = float(config["bed"]["length"])
    floor = 2.0 * float(config["bed"]["radius"])
    if kind == "profile":
        points = np.asarray(s["points"], dtype=np.float64)
        x, z = points[:, 0], points[:, 1]
        for i in range(len(points)):
            where = f"config field 'scenarios.{name}.points[{i}]'"
            if not 0.0 <= x[i] <= length:
                raise ConfigError(
                    f"{where}: x = {x[i]} m is outside the bed (allowed: 0 <= x <= bed.length = {length} m)"
                )
            if i and x[i] <= x[i - 1]:
                raise ConfigError(
                    f"{where}: x = {x[i]} m does not follow x = {x[i - 1]} m of the point before "
                    "(allowed: points sorted by x, each x once)"
                )
            _check_heights(where, z[i : i + 1], floor, top)
        return
    _check_heights(
        f"config field 'scenarios.{name}.file'", read_heightmap(name, s["file"]), floor, top
    )


def _check_heights(where: str, z: np.ndarray, floor: float, top: float) -> None:
    """Refuse heights below ``floor`` (a grain diameter) or above ``top`` (the box), in m."""
    if z.min() < floor:
        raise ConfigError(
            f"{where}: a height of {z.min():.4g} m is below a grain (allowed: >= 2 × bed.radius "
            f"= {floor:.4g} m)"
        )
    if z.max() > top:
        raise ConfigError(
            f"{where}: a height of {z.max():.4g} m is above the bed's box (allowed: <= {top:g} m)"
        )


def check_scenarios(config: Mapping[str, Any], top: float) -> None:
    """:func:`check_terrain` of every scenario of a validated config (``top``: the box's, m)."""
    for name in config["scenarios"]:
        check_terrain(name, config, top)
