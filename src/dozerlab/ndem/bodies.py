"""Non-particle bodies: static planes, static boxes and kinematic boxes (the blade).

Bodies share one numbering (0, 1, … in order of addition). A body's state is its centre (a
plane's reference point), its orientation as a unit quaternion (w, x, y, z), its linear and
angular velocity (zero for static bodies) and, for boxes, the half extents along its local axes.
"""

from __future__ import annotations

import numpy as np

from dozerlab.ndem.contacts import BOX, PLANE

FIELDS = ("kind", "center", "quat", "half", "normal", "vel", "ang", "mu", "kinematic")


def vec3(name: str, value: object) -> np.ndarray:
    """``value`` as a finite float64 (3,) array, or a ValueError naming ``name``."""
    a = np.asarray(value, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return a


def nonnegative(name: str, value: float) -> float:
    """``value`` as a finite float ≥ 0, or a ValueError naming ``name``."""
    v = float(value)
    if not np.isfinite(v) or v < 0.0:
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return v


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (B, 3, 3) whose columns are the local axes, from quaternions (B, 4)."""
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    ).reshape(-1, 3, 3)


class Bodies:
    """The table of planes and boxes, as arrays the kernels read directly."""

    def __init__(self) -> None:
        self.kind = np.zeros(0, dtype=np.int64)
        self.center = np.zeros((0, 3))
        self.quat = np.zeros((0, 4))
        self.half = np.zeros((0, 3))
        self.normal = np.zeros((0, 3))
        self.vel = np.zeros((0, 3))
        self.ang = np.zeros((0, 3))
        self.mu = np.zeros(0)
        self.kinematic = np.zeros(0, dtype=bool)
        self.force = np.zeros((0, 3))
        self.torque = np.zeros((0, 3))
        self.load_center = np.zeros((0, 3))  # centres during the last step (torque reference)

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    def _append(
        self,
        kind: int,
        center: np.ndarray,
        quat: np.ndarray,
        half: np.ndarray,
        normal: np.ndarray,
        mu: float,
        kinematic: bool,
    ) -> int:
        row = {
            "kind": kind,
            "center": center,
            "quat": quat,
            "half": half,
            "normal": normal,
            "vel": np.zeros(3),
            "ang": np.zeros(3),
            "mu": mu,
            "kinematic": kinematic,
        }
        for name in FIELDS:
            old = getattr(self, name)
            setattr(self, name, np.concatenate([old, np.asarray(row[name], old.dtype)[None]]))
        self.force = np.zeros((len(self), 3))
        self.torque = np.zeros((len(self), 3))
        self.load_center = self.center.copy()
        return len(self) - 1

    def add_plane(self, point: object, normal: object, friction: float) -> int:
        """A static half-space boundary through ``point`` whose free side faces ``normal``."""
        n = vec3("normal", normal)
        norm = np.linalg.norm(n)
        if norm == 0.0:
            raise ValueError("normal must be a non-zero vector")
        return self._append(
            PLANE,
            vec3("point", point),
            np.array([1.0, 0, 0, 0]),
            np.zeros(3),
            n / norm,
            nonnegative("friction", friction),
            False,
        )

    def add_box(
        self,
        center: object,
        half_extents: object,
        kinematic: bool,
        friction: float,
        orientation: object | None,
    ) -> int:
        """A box; ``orientation`` is a quaternion (w, x, y, z), identity when None."""
        half = vec3("half_extents", half_extents)
        if np.any(half <= 0.0):
            raise ValueError(f"half_extents must be > 0, got {half.tolist()}")
        q = np.array([1.0, 0, 0, 0]) if orientation is None else np.asarray(orientation, float)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) == 0.0:
            raise ValueError(
                f"orientation must be a non-zero quaternion (w, x, y, z), got {orientation!r}"
            )
        return self._append(
            BOX,
            vec3("center", center),
            q / np.linalg.norm(q),
            half,
            np.zeros(3),
            nonnegative("friction", friction),
            bool(kinematic),
        )

    def check(self, body: int) -> int:
        """``body`` as a valid body index, or a ValueError."""
        b = int(body)
        if not 0 <= b < len(self):
            raise ValueError(f"body must be a body id in [0, {len(self) - 1}], got {body!r}")
        return b

    def check_kinematic(self, body: int) -> int:
        """``body`` as the index of a kinematic box, or a ValueError."""
        b = self.check(body)
        if not self.kinematic[b]:
            raise ValueError(f"body {b} is static; only kinematic boxes (kinematic=True) move")
        return b

    def rotations(self) -> np.ndarray:
        """Rotation matrices (B, 3, 3) of all bodies."""
        return np.ascontiguousarray(quat_to_matrix(self.quat))

    def integrate(self, h: float) -> None:
        """Move kinematic boxes by their velocity over one step of h seconds."""
        for b in np.flatnonzero(self.kinematic):
            self.center[b] += h * self.vel[b]
            w, q = self.ang[b], self.quat[b]
            dq = (
                0.5
                * h
                * np.array(
                    [
                        -w[0] * q[1] - w[1] * q[2] - w[2] * q[3],
                        w[0] * q[0] + w[1] * q[3] - w[2] * q[2],
                        -w[0] * q[3] + w[1] * q[0] + w[2] * q[1],
                        w[0] * q[2] - w[1] * q[1] + w[2] * q[0],
                    ]
                )
            )
            q = q + dq
            self.quat[b] = q / np.linalg.norm(q)
