"""The settled particle bed of a scenario and its file format (``results/beds/{scenario}.npz``).

A bed file is an uncompressed-array ``.npz`` that ``np.load(path, allow_pickle=False)`` reads:
the particle state arrays, the settle log arrays, and ``metadata``, a JSON string with the
scalars and the material (density, friction, …) the bed was built with. NDEM's and the reduced
runs' final states are bed files too. Every array's CRC-32 is checked on loading
(:func:`dozerlab.integrity.read_npz`), and a bed with a non-finite or non-positive particle
value is neither written nor loaded.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab import __version__
from dozerlab.integrity import DamagedFileError, read_npz, require_finite
from dozerlab.runtime import DozerlabError, OutputKind, atomic_output, check_name
from dozerlab.terrain import PRESETS

#: The built-in scenarios (presets); a config may define more (:mod:`dozerlab.terrain`).
SCENARIOS: tuple[str, ...] = PRESETS

_ARRAYS = (
    "positions",
    "radii",
    "masses",
    "velocities",
    "angular_velocities",
    "settle_time",
    "settle_kinetic_energy",
    "settle_contacts",
)


def bed_file_output(path: Path) -> str | None:
    """The command that wrote the bed file at ``path`` (its metadata's ``dozerlab_output``;
    for a file written before that entry, what its ``info`` shows: a reduced run's state names
    its dynamics model, NDEM's holds the time only); None for anything but a bed file."""
    with np.load(path, allow_pickle=False) as data:
        if not {"metadata", *_ARRAYS} <= set(data.files):
            return None
        meta = json.loads(str(data["metadata"]))
    if "dozerlab_output" in meta:
        return str(meta["dozerlab_output"])
    info = meta.get("info", {})
    if "dynamics_model" in info:
        return "reduce-state"
    return "simulate-state" if set(info) == {"time"} else "bed"


def bed_file_kind(what: str, name: str) -> OutputKind:
    """The kind of a bed file that ``name`` writes (``bed``, a run's final state): recognised
    by :func:`bed_file_output`, so a bed is never replaced by a state, nor the other way."""
    return OutputKind(what, lambda path: path.is_file() and bed_file_output(path) == name, name)


#: What ``dozerlab bed`` writes: a ``.npz`` with the bed's metadata and arrays.
BED_FILE = bed_file_kind("a dozerlab bed file (.npz) written by bed", "bed")


@dataclass
class Bed:
    """A settled particle bed.

    Particles (N of them) in id order: ``positions`` (N, 3) m, ``radii`` (N,) m, ``masses`` (N,) kg,
    ``velocities`` and ``angular_velocities`` (N, 3) in m/s and rad/s. The bed spans
    x ∈ [0, length], y ∈ [-width/2, width/2] on the ground z = 0, inside the walls of
    :func:`dozerlab.scenarios.build.make_world`. The settle log samples the build every
    ``bed.log_every`` steps: time (s), mean kinetic energy per particle (J), contacts solved
    (those of awake grains while the pour sleeps the rest, ``bed.active_zone``).
    """

    scenario: str
    length: float
    width: float
    positions: np.ndarray
    radii: np.ndarray
    masses: np.ndarray
    velocities: np.ndarray
    angular_velocities: np.ndarray
    material: dict[str, float]
    seed: int
    settle_time: np.ndarray = field(default_factory=lambda: np.zeros(0))
    settle_kinetic_energy: np.ndarray = field(default_factory=lambda: np.zeros(0))
    settle_contacts: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_name(self.scenario, "Bed.scenario")
        n = len(self.radii)
        for name in ("positions", "velocities", "angular_velocities"):
            arr = np.ascontiguousarray(getattr(self, name), dtype=np.float64)
            if arr.shape != (n, 3):
                raise ValueError(f"Bed.{name} must have shape ({n}, 3), got {arr.shape}")
            setattr(self, name, arr)
        for name in ("radii", "masses", "settle_time", "settle_kinetic_energy"):
            setattr(self, name, np.ascontiguousarray(getattr(self, name), dtype=np.float64))
        self.settle_contacts = np.ascontiguousarray(self.settle_contacts, dtype=np.int64)
        if self.masses.shape != (n,):
            raise ValueError(f"Bed.masses must have shape ({n},), got {self.masses.shape}")

    @property
    def count(self) -> int:
        """Number of particles."""
        return len(self.radii)

    def kinetic_energy_per_particle(self) -> float:
        """Mean translational + rotational kinetic energy per particle in J (solid spheres)."""
        if self.count == 0:
            return 0.0
        lin = 0.5 * self.masses * np.einsum("ij,ij->i", self.velocities, self.velocities)
        inertia = 0.4 * self.masses * self.radii**2
        rot = (
            0.5 * inertia * np.einsum("ij,ij->i", self.angular_velocities, self.angular_velocities)
        )
        return float((lin + rot).mean())

    def jittered(self, jitter: float, seed: int) -> Bed:
        """A twin of this bed: every grain moved by ``jitter`` (m) in a direction drawn from
        ``seed``. Two NDEM runs from a bed and its micrometre twin measure NDEM's own
        run-to-run spread, the floor under any model's error."""
        rng = np.random.default_rng(seed)
        d = rng.normal(size=self.positions.shape)
        d *= jitter / np.linalg.norm(d, axis=1, keepdims=True)
        return replace(self, positions=self.positions + d, info=self.info | {"jitter_m": jitter})

    def check(self, where: str | Path) -> None:
        """Refuse NaN/inf in any array and radii or masses that are not positive
        (:class:`~dozerlab.integrity.DamagedFileError` naming ``where``, the file)."""
        arrays = {name: getattr(self, name) for name in _ARRAYS}
        require_finite(where, arrays, _ARRAYS)
        for name in ("radii", "masses"):
            bad = np.flatnonzero(arrays[name] <= 0)
            if bad.size:
                raise DamagedFileError(
                    f"{where}: '{name}' holds {bad.size} value(s) <= 0, first of particle {bad[0]}"
                )

    def save(self, path: str | Path, kind: OutputKind = BED_FILE) -> None:
        """Write the bed to ``path`` (.npz) atomically, as the output ``kind`` (a bed, a run's
        final state), whose name its metadata records; a bed that fails :meth:`check` is
        refused before anything is written."""
        self.check(path)
        meta = {
            "scenario": self.scenario,
            "length": self.length,
            "width": self.width,
            "material": self.material,
            "seed": self.seed,
            "info": self.info,
            "dozerlab_version": __version__,
            "dozerlab_output": kind.name,
        }
        arrays = {name: getattr(self, name) for name in _ARRAYS}
        with atomic_output(path, kind) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, metadata=np.array(json.dumps(meta)), **arrays)

    @classmethod
    def load(cls, path: str | Path) -> Bed:
        """Read a bed written by :meth:`save` (no pickled data is ever executed)."""
        path = Path(path)
        if not path.is_file():
            raise DozerlabError(f"bed file not found: {path}")
        data = read_npz(path, "a dozerlab bed file", ("metadata", *_ARRAYS))
        try:
            meta = json.loads(str(data["metadata"]))
            bed = cls(
                scenario=meta["scenario"],
                length=float(meta["length"]),
                width=float(meta["width"]),
                material=dict(meta["material"]),
                seed=int(meta["seed"]),
                info=dict(meta.get("info", {})),
                **{name: data[name] for name in _ARRAYS},
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise DozerlabError(f"{path} is not a dozerlab bed file: {exc}") from exc
        bed.check(path)
        return bed
