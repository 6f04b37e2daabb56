"""``World``: spheres and bodies advanced by the SPOOK stepper with a PGS contact solver.

Sphere ids are 0..N-1 in order of addition; every public per-sphere array is in id order.
Internally the spheres are stored sorted by grid cell (re-sorted every step), so the solver
walks memory in spatial order.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.ndem.bodies import Bodies, nonnegative, vec3
from dozerlab.ndem.params import Parameters
from dozerlab.ndem.persist import load_world, save_world
from dozerlab.ndem.state import WorldState
from dozerlab.ndem.stats import StepStats
from dozerlab.ndem.stepper import advance
from dozerlab.ndem.warmstart import WarmStart


def _parameter(name: str) -> Any:
    """A World attribute reading and (validated) setting ``Parameters.name``."""

    def get(self: World) -> Any:
        return getattr(self.params, name)

    def set_(self: World, value: Any) -> None:
        self.params = self.params.with_(**{name: value})

    return property(get, set_, doc=f"``Parameters.{name}`` (settable, validated).")


class World:
    """A granular world. Units SI: m, s, kg, N; arrays float64.

    The keyword arguments are the fields of :class:`~dozerlab.ndem.params.Parameters` (time
    step, solver, material and contact settings, each documented there); those not given take
    their defaults from the config schema. ``dt``, ``iterations`` and ``gravity`` may also be
    passed by position. Every parameter is readable and settable as an attribute (validated).
    The dynamic state (spheres, warm start, clock) is ``state``, a
    :class:`~dozerlab.ndem.state.WorldState`; ``params`` is the current Parameters.
    """

    def __init__(
        self,
        dt: float | None = None,
        iterations: int | None = None,
        gravity: object | None = None,
        **params: Any,
    ) -> None:
        positional: dict[str, Any] = {"dt": dt, "iterations": iterations, "gravity": gravity}
        self.params = Parameters(**{k: v for k, v in positional.items() if v is not None}, **params)
        self.state = WorldState()
        self.bodies = Bodies()
        self.last_stats: StepStats | None = None

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> World:
        """A World from a config's ``solver`` and ``material`` sections (missing: defaults)."""
        world = cls()
        world.params = Parameters.from_config(config)
        return world

    dt = _parameter("dt")
    iterations = _parameter("iterations")
    gravity = _parameter("gravity")
    method = _parameter("method")
    relaxation = _parameter("relaxation")
    tolerance = _parameter("tolerance")
    rest_tolerance = _parameter("rest_tolerance")
    relinearize = _parameter("relinearize")
    relinearize_above = _parameter("relinearize_above")
    damping_steps = _parameter("damping_steps")
    youngs_modulus = _parameter("youngs_modulus")
    poisson_ratio = _parameter("poisson_ratio")
    max_overlap = _parameter("max_overlap")
    density = _parameter("density")
    friction = _parameter("friction")
    rolling_resistance = _parameter("rolling_resistance")
    spinning_resistance = _parameter("spinning_resistance")
    wall_friction = _parameter("wall_friction")
    contact_margin = _parameter("contact_margin")
    slabs = _parameter("slabs")
    warm_start = _parameter("warm_start")
    active_zone = _parameter("active_zone")
    zone_margin = _parameter("zone_margin")
    rest_speed = _parameter("rest_speed")
    rest_time = _parameter("rest_time")
    wake_load = _parameter("wake_load")
    sleeper_compliance = _parameter("sleeper_compliance")

    @property
    def time(self) -> float:
        """Simulated time in s."""
        return self.state.time

    @property
    def step_count(self) -> int:
        """Steps taken."""
        return self.state.step_count

    # ---- spheres -------------------------------------------------------------------------

    def add_spheres(
        self,
        positions: object,
        radius: float | np.ndarray = 0.02,
        density: float | None = None,
        friction: float | None = None,
        rolling_resistance: float | None = None,
        velocities: object | None = None,
        angular_velocities: object | None = None,
    ) -> np.ndarray:
        """Add n spheres at ``positions`` (n, 3) m; returns their ids (n,) int64.

        ``radius`` (m) is a scalar or (n,); density (kg/m³), friction μ and rolling resistance
        μ_r default to the World's. Velocities (n, 3) m/s and angular velocities (n, 3) rad/s
        default to zero.
        """
        x = np.array(positions, dtype=np.float64, ndmin=2)
        if x.ndim != 2 or x.shape[1] != 3:
            raise ValueError(f"positions must have shape (n, 3), got {np.asarray(positions).shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError("positions must be finite (found NaN or inf)")
        n = x.shape[0]
        r = (
            np.broadcast_to(np.asarray(radius, dtype=np.float64), (n,)).copy()
            if np.ndim(radius) == 0 or np.shape(radius) == (n,)
            else None
        )
        if r is None:
            raise ValueError(f"radius must be a scalar or shape ({n},), got {np.shape(radius)}")
        if not np.all(np.isfinite(r) & (r > 0)):
            raise ValueError("radius must be > 0 m and finite")
        rho = self.density if density is None else float(density)
        if not (np.isfinite(rho) and rho > 0):
            raise ValueError(f"density must be > 0 kg/m³, got {density!r}")
        mu = self.friction if friction is None else nonnegative("friction", friction)
        mur = (
            self.rolling_resistance
            if rolling_resistance is None
            else nonnegative("rolling_resistance", rolling_resistance)
        )
        v = self._vectors("velocities", velocities, n)
        w = self._vectors("angular_velocities", angular_velocities, n)
        ids = np.arange(self.n_spheres, self.n_spheres + n, dtype=np.int64)
        self.state.append(
            x=x,
            v=v,
            w=w,
            r=r,
            m=rho * 4.0 / 3.0 * np.pi * r**3,
            mu=np.full(n, mu),
            mur=np.full(n, mur),
            id=ids,
        )
        return ids

    def count_as_rested(self) -> int:
        """Start the rest clock of every sphere slower than ``rest_speed`` (its centre, and its
        surface from spin) at ``rest_time``, as though it had rested that long already: for a
        bed that settled before this world held it. With the active zone, those outside the
        zone then sleep after the first step, not after ``rest_time`` of steps that solve the
        whole resting bed. Returns how many were counted so."""
        st = self.state
        s2 = self.rest_speed**2
        still = (np.einsum("ij,ij->i", st.v, st.v) <= s2) & (
            np.einsum("ij,ij->i", st.w, st.w) * st.r**2 <= s2
        )
        st.rest[still] = np.maximum(st.rest[still], self.rest_time)
        return int(still.sum())

    @staticmethod
    def _vectors(name: str, value: object | None, n: int) -> np.ndarray:
        if value is None:
            return np.zeros((n, 3))
        a = np.array(value, dtype=np.float64)
        if a.shape != (n, 3) or not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite with shape ({n}, 3), got {a.shape}")
        return a

    def remove_spheres(self, mask_or_ids: object) -> np.ndarray:
        """Remove spheres given by a boolean mask (N,) or ids; returns the kept old ids.

        The remaining spheres are renumbered 0..M-1 keeping their order: new id k is old id
        ``kept[k]``. Warm-start data is dropped.
        """
        sel = np.asarray(mask_or_ids)
        drop = np.zeros(self.n_spheres, dtype=bool)
        if sel.dtype == bool:
            if sel.shape != (self.n_spheres,):
                raise ValueError(f"mask must have shape ({self.n_spheres},), got {sel.shape}")
            drop = sel.copy()
        else:
            ids = sel.astype(np.int64).ravel()
            if ids.size and (ids.min() < 0 or ids.max() >= self.n_spheres):
                raise ValueError(f"ids must be in [0, {self.n_spheres - 1}]")
            drop[ids] = True
        st = self.state
        st.reorder(~drop[st.id])
        new_id = np.cumsum(~drop) - 1
        st.id = new_id[st.id]
        st.warm = WarmStart()
        return np.flatnonzero(~drop)

    @property
    def n_spheres(self) -> int:
        """Number of spheres N."""
        return self.state.n

    def _assign(self, name: str, value: object) -> None:
        a = self._vectors(name, value, self.n_spheres)
        field = {"positions": "x", "velocities": "v", "angular_velocities": "w"}[name]
        getattr(self.state, field)[:] = a[self.state.id]

    positions = property(
        lambda self: self.state.public(self.state.x),
        lambda self, a: self._assign("positions", a),
        doc="Sphere centres (N, 3) m in id order (a copy; assign to set).",
    )
    velocities = property(
        lambda self: self.state.public(self.state.v),
        lambda self, a: self._assign("velocities", a),
        doc="Sphere velocities (N, 3) m/s in id order (a copy; assign to set).",
    )
    angular_velocities = property(
        lambda self: self.state.public(self.state.w),
        lambda self, a: self._assign("angular_velocities", a),
        doc="Sphere angular velocities (N, 3) rad/s in id order (a copy; assign to set).",
    )
    radii = property(lambda self: self.state.public(self.state.r), doc="Radii (N,) m in id order.")
    masses = property(
        lambda self: self.state.public(self.state.m), doc="Masses (N,) kg in id order."
    )

    def set_sphere_state(
        self,
        ids: object,
        positions: object | None = None,
        velocities: object | None = None,
        angular_velocities: object | None = None,
    ) -> None:
        """Overwrite the state of spheres ``ids`` (k,); each given array is (k, 3)."""
        ids = np.asarray(ids, dtype=np.int64).ravel()
        if ids.size and (ids.min() < 0 or ids.max() >= self.n_spheres):
            raise ValueError(f"ids must be in [0, {self.n_spheres - 1}]")
        slot = self.state.slots()
        for name, value, arr in (
            ("positions", positions, self.state.x),
            ("velocities", velocities, self.state.v),
            ("angular_velocities", angular_velocities, self.state.w),
        ):
            if value is not None:
                arr[slot[ids]] = self._vectors(name, value, ids.size)

    # ---- bodies --------------------------------------------------------------------------

    def add_plane(
        self,
        point: object = (0.0, 0.0, 0.0),
        normal: object = (0.0, 0.0, 1.0),
        friction: float | None = None,
    ) -> int:
        """A static plane through ``point`` (m); spheres stay on the side ``normal`` faces."""
        return self.bodies.add_plane(
            point, normal, self.wall_friction if friction is None else friction
        )

    def add_box(
        self,
        center: object,
        half_extents: object,
        kinematic: bool = False,
        friction: float | None = None,
        orientation: object | None = None,
    ) -> int:
        """A box (static, or kinematic when its velocity is prescribed); returns its body id.

        ``center`` and ``half_extents`` (3,) in m; ``orientation`` a quaternion (w, x, y, z).
        """
        return self.bodies.add_box(
            center,
            half_extents,
            kinematic,
            self.wall_friction if friction is None else friction,
            orientation,
        )

    def set_velocity(self, body: int, linear: object, angular: object | None = None) -> None:
        """Prescribe a kinematic box's velocity (m/s) and angular velocity (rad/s, None: zero)."""
        b = self.bodies.check_kinematic(body)
        self.bodies.vel[b] = vec3("linear", linear)
        self.bodies.ang[b] = np.zeros(3) if angular is None else vec3("angular", angular)

    def set_body_pose(self, body: int, center: object, orientation: object | None = None) -> None:
        """Place a kinematic box: centre (3,) m and, if given, quaternion (w, x, y, z)."""
        b = self.bodies.check_kinematic(body)
        self.bodies.center[b] = vec3("center", center)
        if orientation is not None:
            q = np.asarray(orientation, dtype=np.float64)
            if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) == 0:
                raise ValueError(f"orientation must be a non-zero quaternion, got {orientation!r}")
            self.bodies.quat[b] = q / np.linalg.norm(q)

    def body_position(self, body: int) -> np.ndarray:
        """Centre (3,) m of a box, or a plane's reference point."""
        return self.bodies.center[self.bodies.check(body)].copy()

    def body_orientation(self, body: int) -> np.ndarray:
        """Orientation quaternion (w, x, y, z) of a body."""
        return self.bodies.quat[self.bodies.check(body)].copy()

    def body_velocity(self, body: int) -> np.ndarray:
        """Linear velocity (3,) m/s of a body (zero for static ones)."""
        return self.bodies.vel[self.bodies.check(body)].copy()

    def body_angular_velocity(self, body: int) -> np.ndarray:
        """Angular velocity (3,) rad/s of a body."""
        return self.bodies.ang[self.bodies.check(body)].copy()

    def force_on(self, body: int) -> np.ndarray:
        """Total contact force (3,) N the spheres put on ``body`` during the last step."""
        return self.bodies.force[self.bodies.check(body)].copy()

    def torque_on(self, body: int, about: object | None = None) -> np.ndarray:
        """Contact torque (3,) N·m on ``body`` in the last step, about its centre or ``about``.

        The moment is taken about the body's centre as it was during the step.
        """
        b = self.bodies.check(body)
        t = self.bodies.torque[b].copy()
        if about is not None:
            t += np.cross(self.bodies.load_center[b] - vec3("about", about), self.bodies.force[b])
        return t

    @property
    def contact_count(self) -> int:
        """Touching contacts in the last step."""
        return 0 if self.last_stats is None else self.last_stats.contacts

    # ---- stepping ------------------------------------------------------------------------

    def step(self, n: int = 1) -> StepStats:
        """Advance ``n`` steps of dt; returns the last step's stats (also ``last_stats``)."""
        if int(n) != n or n < 1:
            raise ValueError(f"n must be an integer >= 1, got {n!r}")
        for _ in range(int(n)):
            stats = advance(self.state, self.bodies, self.params)
        self.last_stats = stats
        return stats

    # ---- persistence ---------------------------------------------------------------------

    def save(self, path: str | Path) -> None:
        """Write the whole state (spheres, bodies, warm start, parameters) to a ``.npz``."""
        save_world(path, self.params, self.state, self.bodies)

    @classmethod
    def load(cls, path: str | Path) -> World:
        """A World read back from :meth:`save`'s file."""
        world = cls()
        world.params, world.state, world.bodies = load_world(path)
        return world

    def __repr__(self) -> str:
        return (
            f"World(spheres={self.n_spheres}, bodies={len(self.bodies)}, dt={self.dt}, "
            f"iterations={self.iterations}, time={self.time:.4g})"
        )
