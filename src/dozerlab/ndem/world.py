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
from dozerlab.ndem.stats import StepStats
from dozerlab.ndem.stepper import advance
from dozerlab.ndem.warmstart import WarmStart

SPHERE_FIELDS = ("_x", "_v", "_w", "_r", "_m", "_mu", "_mur", "_id")


class World:
    """A granular world. Units SI: m, s, kg, N; arrays float64.

    Args:
        dt: time step h in s (> 0).
        iterations: PGS iterations per step (≥ 1).
        gravity: (3,) m/s².
        damping_steps: SPOOK damping time τ in steps (τ = damping_steps·dt, > 0).
        youngs_modulus: E in Pa for the Hertz-mapped compliance; 0 makes contacts stiff.
        poisson_ratio: ν in [0, 0.5).
        max_overlap: overlap over the smaller radius beyond which a step raises DivergenceError.
        density, friction, rolling_resistance: defaults of ``add_spheres`` (kg/m³, μ, μ_r).
        wall_friction: default friction μ of planes and boxes.
        contact_margin: near contacts with a gap below this fraction of the smallest radius are
            solved too (speculatively), so fast particles stop at contact instead of overlapping.
        slabs: slabs of the parallel sweep (more than the thread count balances the load; the
            result depends on this number, never on the thread count).
        warm_start: start each step's solve from the last step's multipliers of persisting
            contacts.
    """

    def __init__(
        self,
        dt: float = 0.01,
        iterations: int = 50,
        gravity: tuple[float, float, float] = (0.0, 0.0, -9.81),
        *,
        damping_steps: float = 3.0,
        youngs_modulus: float = 1.0e8,
        poisson_ratio: float = 0.3,
        max_overlap: float = 0.5,
        density: float = 2600.0,
        friction: float = 0.5,
        rolling_resistance: float = 0.1,
        wall_friction: float = 0.5,
        contact_margin: float = 0.02,
        slabs: int = 16,
        warm_start: bool = True,
    ) -> None:
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be > 0 s, got {dt!r}")
        if not (np.isfinite(damping_steps) and damping_steps > 0):
            raise ValueError(f"damping_steps must be > 0, got {damping_steps!r}")
        if not 0.0 <= poisson_ratio < 0.5:
            raise ValueError(f"poisson_ratio must be in [0, 0.5), got {poisson_ratio!r}")
        if not (np.isfinite(max_overlap) and max_overlap > 0):
            raise ValueError(f"max_overlap must be > 0, got {max_overlap!r}")
        if not (np.isfinite(density) and density > 0):
            raise ValueError(f"density must be > 0 kg/m³, got {density!r}")
        if int(slabs) < 1:
            raise ValueError(f"slabs must be >= 1, got {slabs!r}")
        self.dt = float(dt)
        self.iterations = iterations
        self.gravity = vec3("gravity", gravity)
        self.damping_steps = float(damping_steps)
        self.youngs_modulus = nonnegative("youngs_modulus", youngs_modulus)
        self.poisson_ratio = float(poisson_ratio)
        self.max_overlap = float(max_overlap)
        self.density = float(density)
        self.friction = nonnegative("friction", friction)
        self.rolling_resistance = nonnegative("rolling_resistance", rolling_resistance)
        self.wall_friction = nonnegative("wall_friction", wall_friction)
        self.contact_margin = nonnegative("contact_margin", contact_margin)
        self.slabs = int(slabs)
        self.warm_start = bool(warm_start)
        self.time = 0.0
        self.step_count = 0
        self.bodies = Bodies()
        self._warm = WarmStart()
        self.last_stats: StepStats | None = None
        # Per-sphere storage in slot (spatially sorted) order; _id maps slot → sphere id.
        self._x = np.zeros((0, 3))
        self._v = np.zeros((0, 3))
        self._w = np.zeros((0, 3))
        self._r = np.zeros(0)
        self._m = np.zeros(0)
        self._mu = np.zeros(0)
        self._mur = np.zeros(0)
        self._id = np.zeros(0, dtype=np.int64)

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> World:
        """A World from a validated config's ``solver`` and ``material`` sections."""
        s, m = config.get("solver", {}), config.get("material", {})
        return cls(
            dt=s.get("dt", 0.01),
            iterations=s.get("iterations", 50),
            gravity=tuple(s.get("gravity", (0.0, 0.0, -9.81))),
            damping_steps=s.get("damping_steps", 3.0),
            max_overlap=s.get("max_overlap", 0.5),
            density=m.get("density", 2600.0),
            youngs_modulus=m.get("youngs_modulus", 1.0e8),
            poisson_ratio=m.get("poisson_ratio", 0.3),
            friction=m.get("friction", 0.5),
            rolling_resistance=m.get("rolling_resistance", 0.1),
            wall_friction=m.get("wall_friction", 0.5),
        )

    @property
    def iterations(self) -> int:
        """PGS iterations per step (settable, ≥ 1)."""
        return self._iterations

    @iterations.setter
    def iterations(self, value: int) -> None:
        if int(value) != value or int(value) < 1:
            raise ValueError(f"iterations must be an integer >= 1, got {value!r}")
        self._iterations = int(value)

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
            raise ValueError(f"positions must have shape (n, 3), got {np.shape(positions)}")
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
        ids = np.arange(len(self._id), len(self._id) + n, dtype=np.int64)
        new = {
            "_x": x,
            "_v": v,
            "_w": w,
            "_r": r,
            "_m": rho * 4.0 / 3.0 * np.pi * r**3,
            "_mu": np.full(n, mu),
            "_mur": np.full(n, mur),
            "_id": ids,
        }
        for f in SPHERE_FIELDS:
            setattr(self, f, np.concatenate([getattr(self, f), new[f]]))
        return ids

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
        keep_slot = ~drop[self._id]
        for f in SPHERE_FIELDS:
            setattr(self, f, np.ascontiguousarray(getattr(self, f)[keep_slot]))
        new_id = np.cumsum(~drop) - 1
        self._id = new_id[self._id]
        self._warm = WarmStart()
        return np.flatnonzero(~drop)

    @property
    def n_spheres(self) -> int:
        """Number of spheres N."""
        return int(self._id.shape[0])

    def _public(self, a: np.ndarray) -> np.ndarray:
        out = np.empty_like(a)
        out[self._id] = a
        return out

    def _assign(self, name: str, value: object) -> None:
        a = self._vectors(name, value, self.n_spheres)
        field = {"positions": "_x", "velocities": "_v", "angular_velocities": "_w"}[name]
        getattr(self, field)[:] = a[self._id]

    positions = property(
        lambda self: self._public(self._x),
        lambda self, a: self._assign("positions", a),
        doc="Sphere centres (N, 3) m in id order (a copy; assign to set).",
    )
    velocities = property(
        lambda self: self._public(self._v),
        lambda self, a: self._assign("velocities", a),
        doc="Sphere velocities (N, 3) m/s in id order (a copy; assign to set).",
    )
    angular_velocities = property(
        lambda self: self._public(self._w),
        lambda self, a: self._assign("angular_velocities", a),
        doc="Sphere angular velocities (N, 3) rad/s in id order (a copy; assign to set).",
    )
    radii = property(lambda self: self._public(self._r), doc="Radii (N,) m in id order.")
    masses = property(lambda self: self._public(self._m), doc="Masses (N,) kg in id order.")

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
        slot = np.empty(self.n_spheres, dtype=np.int64)
        slot[self._id] = np.arange(self.n_spheres)
        for name, value, arr in (
            ("positions", positions, self._x),
            ("velocities", velocities, self._v),
            ("angular_velocities", angular_velocities, self._w),
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
            self.last_stats = advance(self)
        return self.last_stats

    # ---- persistence ---------------------------------------------------------------------

    def save(self, path: str | Path) -> None:
        """Write the whole state (spheres, bodies, warm start, parameters) to a ``.npz``."""
        from dozerlab.ndem.state import save_world

        save_world(self, path)

    @classmethod
    def load(cls, path: str | Path) -> World:
        """A World read back from :meth:`save`'s file."""
        from dozerlab.ndem.state import load_world

        return load_world(path)

    def __repr__(self) -> str:
        return (
            f"World(spheres={self.n_spheres}, bodies={len(self.bodies)}, dt={self.dt}, "
            f"iterations={self.iterations}, time={self.time:.4g})"
        )
