"""Saving and loading a World's parts as one ``.npz`` (no pickles), e.g. to reuse a settled bed.

Loading checks every array's CRC-32 (:func:`dozerlab.integrity.read_npz`) and refuses NaN/inf
in the parameters and the sphere state; saving refuses a state holding them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.integrity import read_npz, require_finite
from dozerlab.ndem.bodies import FIELDS as BODY_FIELDS
from dozerlab.ndem.bodies import Bodies
from dozerlab.ndem.params import NAMES, Parameters
from dozerlab.ndem.state import SPHERE_FIELDS, ZONE_FIELDS, WorldState
from dozerlab.runtime import DozerlabError, OutputKind, atomic_output, npz_with

FORMAT_VERSION = 1
# Parameters written as param_NAME scalars (gravity is a (3,) array of its own); files written
# before a parameter existed load with its default.
SCALARS = tuple(n for n in NAMES if n != "gravity")
#: What :func:`save_world` writes (recognised by its format version and parameters).
WORLD_FILE = OutputKind("a dozerlab World file (.npz)", npz_with(("format_version", "param_dt")))


def save_world(path: str | Path, params: Parameters, state: WorldState, bodies: Bodies) -> None:
    """Write a World's parameters, state and bodies to ``path`` (.npz) atomically."""
    arrays: dict[str, Any] = {"format_version": np.array(FORMAT_VERSION)}
    arrays |= {f"param_{p}": np.array(getattr(params, p)) for p in SCALARS}
    arrays |= {"param_gravity": params.gravity}
    arrays |= {"param_time": np.array(state.time), "param_step_count": np.array(state.step_count)}
    arrays |= {f"sphere_{f}": getattr(state, f) for f in SPHERE_FIELDS + ZONE_FIELDS}
    arrays |= {f"body_{f}": getattr(bodies, f) for f in BODY_FIELDS}
    arrays |= {
        "body_force": bodies.force,
        "body_torque": bodies.torque,
        "warm_start": state.warm.start,
        "warm_hi": state.warm.hi,
        "warm_lam": state.warm.lam,
    }
    require_finite(path, arrays, [k for k in arrays if k.startswith(("param_", "sphere_"))])
    with atomic_output(path, WORLD_FILE) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


def load_world(path: str | Path) -> tuple[Parameters, WorldState, Bodies]:
    """The parameters, state and bodies in a file written by :func:`save_world`."""
    f = read_npz(path, "a dozerlab.ndem World file", ())
    if "format_version" not in f or int(f["format_version"]) != FORMAT_VERSION:
        raise DozerlabError(f"{path} is not a dozerlab.ndem World file (format {FORMAT_VERSION})")
    require_finite(path, f, [k for k in f if k.startswith(("param_", "sphere_"))])
    try:
        given = {p: f[f"param_{p}"].item() for p in SCALARS if f"param_{p}" in f}
        params = Parameters(**given, gravity=f["param_gravity"])
        state = WorldState(time=float(f["param_time"]), step_count=int(f["param_step_count"]))
        for name in SPHERE_FIELDS:
            setattr(state, name, np.ascontiguousarray(f[f"sphere_{name}"]))
        # files from before the active zone: every sphere awake, none resting
        n = state.n
        state.awake = (
            f["sphere_awake"].astype(np.bool_) if "sphere_awake" in f else np.ones(n, np.bool_)
        )
        state.rest = f["sphere_rest"].astype(np.float64) if "sphere_rest" in f else np.zeros(n)
        state.warm.start = f["warm_start"].copy()
        state.warm.hi = f["warm_hi"].copy()
        state.warm.lam = f["warm_lam"].copy()
        bodies = Bodies()
        for name in BODY_FIELDS:
            setattr(bodies, name, np.ascontiguousarray(f[f"body_{name}"]))
        bodies.force = f["body_force"].copy()
        bodies.torque = f["body_torque"].copy()
        bodies.load_center = bodies.center.copy()
    except KeyError as exc:
        raise DozerlabError(f"{path} is not a dozerlab.ndem World file: it lacks {exc}") from exc
    return params, state, bodies
