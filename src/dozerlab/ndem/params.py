"""The engine's parameters as one typed, validated object; defaults from the config schema.

The schema (``workflow/schemas/config.schema.yaml``) is the one source of the defaults of the
``solver`` and ``material`` sections; the engine-only knobs (contact margin, slabs, warm start)
have theirs here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from functools import cache
from typing import Any

import numpy as np

from dozerlab.ndem.bodies import nonnegative, vec3

# The solver's methods; the order is their numeric code in the kernels.
METHODS = ("pgs", "nncg")

SOLVER_KEYS = (
    "dt",
    "iterations",
    "gravity",
    "damping_steps",
    "max_overlap",
    "method",
    "relaxation",
    "tolerance",
    "rest_tolerance",
    "relinearize",
    "relinearize_above",
)
# solver.active_zone's keys and the Parameters fields they fill.
ZONE_KEYS = {
    "enabled": "active_zone",
    "margin": "zone_margin",
    "rest_speed": "rest_speed",
    "rest_time": "rest_time",
    "wake_load": "wake_load",
    "sleeper_compliance": "sleeper_compliance",
}
MATERIAL_KEYS = (
    "density",
    "youngs_modulus",
    "poisson_ratio",
    "friction",
    "rolling_resistance",
    "spinning_resistance",
    "wall_friction",
)


@cache
def schema_defaults() -> dict[str, Any]:
    """Defaults of the ``solver`` and ``material`` sections, read from the config schema."""
    from dozerlab.config import load_config

    full = load_config(None)
    zone = full["solver"]["active_zone"]
    return (
        {k: full["solver"][k] for k in SOLVER_KEYS}
        | {k: full["material"][k] for k in MATERIAL_KEYS}
        | {name: zone[k] for k, name in ZONE_KEYS.items()}
    )


def _schema(name: str) -> Callable[[], Any]:
    """A default factory reading ``name``'s default from the schema when a Parameters is made."""
    return lambda: schema_defaults()[name]


@dataclass(frozen=True, eq=False)
class Parameters:
    """What a World is: its time step, solver and contact-model settings (SI units).

    dt: time step h in s (> 0); iterations: solver sweeps per step at most (≥ 1); method:
    ``pgs`` or ``nncg`` (:data:`METHODS`); relaxation: ω scaling every row update, in (0, 2)
    (> 1: over-relaxation, projected SOR); tolerance: the RMS velocity change in m/s of a sweep's
    updates at the contact points below which a step's solve stops early (0: always run
    ``iterations``); rest_tolerance: in a step in which no body moves, the solve also stops
    after a sweep that changed the velocity at every contact point by at most this, m/s (0:
    never); relinearize: rounds (≥ 0) in which the Hertz rows whose pairs sink past the
    overlap their compliance was taken at are taken again there and the solve continues, in the
    steps where some pair would end deeper than relinearize_above of its smaller radius (≥ 0);
    gravity (3,) m/s²; damping_steps: SPOOK damping time τ in steps (> 0); youngs_modulus E in Pa (0: stiff contacts);
    poisson_ratio ν in [0, 0.5); max_overlap: overlap over the smaller radius that raises
    DivergenceError; density (kg/m³), friction μ and rolling_resistance μ_r: sphere defaults;
    wall_friction: body default μ; contact_margin: speculative gap as a fraction of the smallest
    radius; slabs: parallel sweep partitions (the result depends on it, not on threads);
    warm_start: start from the last step's multipliers; active_zone: step only the grains that
    can move (``solver.active_zone``), grains at rest outside the moving boxes grown by
    zone_margin (m) sleeping once slower than rest_speed (m/s) for rest_time (s), and a sleeper
    waking when the awake grains' normal impulses on it pass wake_load (≥ 1) times those of its
    resting contacts; a Hertz contact of an awake grain with a sleeper sleeper_compliance (≥ 1)
    times as compliant as its own.
    """

    dt: float = field(default_factory=_schema("dt"))
    iterations: int = field(default_factory=_schema("iterations"))
    gravity: np.ndarray = field(default_factory=_schema("gravity"))
    method: str = field(default_factory=_schema("method"))
    relaxation: float = field(default_factory=_schema("relaxation"))
    tolerance: float = field(default_factory=_schema("tolerance"))
    rest_tolerance: float = field(default_factory=_schema("rest_tolerance"))
    relinearize: int = field(default_factory=_schema("relinearize"))
    relinearize_above: float = field(default_factory=_schema("relinearize_above"))
    damping_steps: float = field(default_factory=_schema("damping_steps"))
    youngs_modulus: float = field(default_factory=_schema("youngs_modulus"))
    poisson_ratio: float = field(default_factory=_schema("poisson_ratio"))
    max_overlap: float = field(default_factory=_schema("max_overlap"))
    density: float = field(default_factory=_schema("density"))
    friction: float = field(default_factory=_schema("friction"))
    rolling_resistance: float = field(default_factory=_schema("rolling_resistance"))
    spinning_resistance: float = field(default_factory=_schema("spinning_resistance"))
    wall_friction: float = field(default_factory=_schema("wall_friction"))
    contact_margin: float = 0.02
    slabs: int = 16
    warm_start: bool = True
    active_zone: bool = field(default_factory=_schema("active_zone"))
    zone_margin: float = field(default_factory=_schema("zone_margin"))
    rest_speed: float = field(default_factory=_schema("rest_speed"))
    rest_time: float = field(default_factory=_schema("rest_time"))
    wake_load: float = field(default_factory=_schema("wake_load"))
    sleeper_compliance: float = field(default_factory=_schema("sleeper_compliance"))

    def __post_init__(self) -> None:
        def put(name: str, value: object) -> None:
            object.__setattr__(self, name, value)

        dt, damping, pr = self.dt, self.damping_steps, self.poisson_ratio
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be > 0 s, got {dt!r}")
        if int(self.iterations) != self.iterations or int(self.iterations) < 1:
            raise ValueError(f"iterations must be an integer >= 1, got {self.iterations!r}")
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if not 0.0 < self.relaxation < 2.0:
            raise ValueError(f"relaxation must be in (0, 2), got {self.relaxation!r}")
        if not (np.isfinite(damping) and damping > 0):
            raise ValueError(f"damping_steps must be > 0, got {damping!r}")
        if not 0.0 <= pr < 0.5:
            raise ValueError(f"poisson_ratio must be in [0, 0.5), got {pr!r}")
        if not (np.isfinite(self.max_overlap) and self.max_overlap > 0):
            raise ValueError(f"max_overlap must be > 0, got {self.max_overlap!r}")
        if not (np.isfinite(self.density) and self.density > 0):
            raise ValueError(f"density must be > 0 kg/m³, got {self.density!r}")
        if int(self.slabs) < 1:
            raise ValueError(f"slabs must be >= 1, got {self.slabs!r}")
        put("dt", float(dt))
        put("iterations", int(self.iterations))
        put("relaxation", float(self.relaxation))
        put("tolerance", nonnegative("tolerance", self.tolerance))
        put("rest_tolerance", nonnegative("rest_tolerance", self.rest_tolerance))
        if int(self.relinearize) != self.relinearize or int(self.relinearize) < 0:
            raise ValueError(f"relinearize must be an integer >= 0, got {self.relinearize!r}")
        put("relinearize", int(self.relinearize))
        put("relinearize_above", nonnegative("relinearize_above", self.relinearize_above))
        put("gravity", vec3("gravity", self.gravity))
        put("damping_steps", float(damping))
        put("poisson_ratio", float(pr))
        put("max_overlap", float(self.max_overlap))
        put("density", float(self.density))
        for name in (
            "youngs_modulus",
            "friction",
            "rolling_resistance",
            "spinning_resistance",
            "wall_friction",
        ):
            put(name, nonnegative(name, getattr(self, name)))
        put("contact_margin", nonnegative("contact_margin", self.contact_margin))
        put("slabs", int(self.slabs))
        put("warm_start", bool(self.warm_start))
        put("active_zone", bool(self.active_zone))
        for name in ("zone_margin", "rest_speed", "rest_time"):
            put(name, nonnegative(name, getattr(self, name)))
        if not (np.isfinite(self.wake_load) and self.wake_load >= 1.0):
            raise ValueError(f"wake_load must be >= 1, got {self.wake_load!r}")
        put("wake_load", float(self.wake_load))
        if not (np.isfinite(self.sleeper_compliance) and self.sleeper_compliance >= 1.0):
            raise ValueError(f"sleeper_compliance must be >= 1, got {self.sleeper_compliance!r}")
        put("sleeper_compliance", float(self.sleeper_compliance))

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> Parameters:
        """Parameters from a config's ``solver`` and ``material`` sections (missing: defaults)."""
        s, m = config.get("solver", {}), config.get("material", {})
        zone = s.get("active_zone", {})
        given = (
            {k: s[k] for k in SOLVER_KEYS if k in s}
            | {k: m[k] for k in MATERIAL_KEYS if k in m}
            | {name: zone[k] for k, name in ZONE_KEYS.items() if k in zone}
        )
        return cls(**given)

    def with_(self, **changes: Any) -> Parameters:
        """A validated copy with ``changes``."""
        return replace(self, **changes)


NAMES = tuple(f.name for f in fields(Parameters))
