"""Saving and loading a World as one ``.npz`` (no pickles), e.g. to reuse a settled bed."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dozerlab.ndem.bodies import FIELDS as BODY_FIELDS
from dozerlab.ndem.world import SPHERE_FIELDS, World
from dozerlab.runtime import DozerlabError, OutputKind, atomic_output, npz_with

FORMAT_VERSION = 1
#: What :func:`save_world` writes (recognised by its format version and parameters).
WORLD_FILE = OutputKind("a dozerlab World file (.npz)", npz_with(("format_version", "param_dt")))
PARAMETERS = (
    "dt",
    "iterations",
    "damping_steps",
    "youngs_modulus",
    "poisson_ratio",
    "max_overlap",
    "density",
    "friction",
    "rolling_resistance",
    "wall_friction",
    "contact_margin",
    "slabs",
    "warm_start",
    "time",
    "step_count",
)


def save_world(world: World, path: str | Path) -> None:
    """Write ``world`` to ``path`` (.npz) atomically."""
    arrays: dict[str, np.ndarray] = {"format_version": np.array(FORMAT_VERSION)}
    arrays |= {f"param_{p}": np.array(getattr(world, p)) for p in PARAMETERS}
    arrays["param_gravity"] = world.gravity
    arrays |= {f"sphere{f}": getattr(world, f) for f in SPHERE_FIELDS}
    arrays |= {f"body_{f}": getattr(world.bodies, f) for f in BODY_FIELDS}
    arrays |= {
        "body_force": world.bodies.force,
        "body_torque": world.bodies.torque,
        "warm_start": world._warm.start,
        "warm_hi": world._warm.hi,
        "warm_lam": world._warm.lam,
    }
    with atomic_output(path, WORLD_FILE) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


def load_world(path: str | Path) -> World:
    """Read a World written by :func:`save_world`."""
    with np.load(path, allow_pickle=False) as f:
        if "format_version" not in f or int(f["format_version"]) != FORMAT_VERSION:
            raise DozerlabError(
                f"{path} is not a dozerlab.ndem World file (format {FORMAT_VERSION})"
            )
        p = {name: f[f"param_{name}"].item() for name in PARAMETERS}
        world = World(
            **{k: v for k, v in p.items() if k not in ("time", "step_count")},
            gravity=tuple(f["param_gravity"]),
        )
        world.time, world.step_count = float(p["time"]), int(p["step_count"])
        for name in SPHERE_FIELDS:
            setattr(world, name, np.ascontiguousarray(f[f"sphere{name}"]))
        for name in BODY_FIELDS:
            setattr(world.bodies, name, np.ascontiguousarray(f[f"body_{name}"]))
        world.bodies.force = f["body_force"].copy()
        world.bodies.torque = f["body_torque"].copy()
        world.bodies.load_center = world.bodies.center.copy()
        world._warm.start = f["warm_start"].copy()
        world._warm.hi = f["warm_hi"].copy()
        world._warm.lam = f["warm_lam"].copy()
    return world
