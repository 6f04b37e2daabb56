"""A World's dynamic state: the spheres in slot order, the warm start and the clock.

Spheres are stored sorted by grid cell (the stepper re-sorts them every step), so the solver
walks memory in spatial order; ``id`` maps slot → sphere id.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from dozerlab.ndem.warmstart import WarmStart

# The per-sphere arrays, all in slot order: centre (N, 3) m, velocity (N, 3) m/s, angular
# velocity (N, 3) rad/s, radius (N,) m, mass (N,) kg, friction μ (N,), rolling resistance (N,),
# sphere id (N,) int64.
SPHERE_FIELDS = ("x", "v", "w", "r", "m", "mu", "mur", "id")
# The active zone's per-sphere arrays, in slot order: awake (N,) bool (False: asleep, held
# still) and the time at rest outside the zone (N,) s. New spheres are awake.
ZONE_FIELDS = ("awake", "rest")


@njit(cache=True)
def _gather(perm, x, v, w, r, m, mu, mur, ids):
    """Each array's rows ``perm`` (M,) in that order, as new arrays (x[perm], v[perm], ...)."""
    n = perm.shape[0]
    x2, v2, w2 = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
    r2, m2, mu2, mur2 = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    ids2 = np.empty(n, dtype=np.int64)
    for k in range(n):
        i = perm[k]
        if i < 0 or i >= x.shape[0]:
            raise IndexError("reorder: slot out of range")
        for a in range(3):
            x2[k, a] = x[i, a]
            v2[k, a] = v[i, a]
            w2[k, a] = w[i, a]
        r2[k], m2[k], mu2[k], mur2[k], ids2[k] = r[i], m[i], mu[i], mur[i], ids[i]
    return x2, v2, w2, r2, m2, mu2, mur2, ids2


def _vectors() -> np.ndarray:
    return np.zeros((0, 3))


def _scalars() -> np.ndarray:
    return np.zeros(0)


@dataclass
class WorldState:
    """Everything a step changes besides the bodies (see :data:`SPHERE_FIELDS`)."""

    x: np.ndarray = field(default_factory=_vectors)
    v: np.ndarray = field(default_factory=_vectors)
    w: np.ndarray = field(default_factory=_vectors)
    r: np.ndarray = field(default_factory=_scalars)
    m: np.ndarray = field(default_factory=_scalars)
    mu: np.ndarray = field(default_factory=_scalars)
    mur: np.ndarray = field(default_factory=_scalars)
    id: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    awake: np.ndarray = field(default_factory=lambda: np.ones(0, dtype=np.bool_))
    rest: np.ndarray = field(default_factory=_scalars)
    warm: WarmStart = field(default_factory=WarmStart)
    time: float = 0.0
    step_count: int = 0

    @property
    def n(self) -> int:
        """Number of spheres N."""
        return int(self.id.shape[0])

    def reorder(self, index: np.ndarray) -> None:
        """Keep the slots ``index`` (a permutation, or a boolean mask) in that order.

        An int64 index must name slots in 0..N-1 (IndexError otherwise, no wrap-around)."""
        floats = (self.x, self.v, self.w, self.r, self.m, self.mu, self.mur)
        if index.dtype == np.int64 and all(a.dtype == np.float64 for a in floats):
            # The per-step re-sort: every field gathered in one pass over the permutation.
            (self.x, self.v, self.w, self.r, self.m, self.mu, self.mur, self.id) = _gather(
                index, self.x, self.v, self.w, self.r, self.m, self.mu, self.mur, self.id
            )
            self.awake, self.rest = self.awake[index], self.rest[index]
            return
        for f in SPHERE_FIELDS + ZONE_FIELDS:
            setattr(self, f, np.ascontiguousarray(getattr(self, f)[index]))

    def append(self, **arrays: np.ndarray) -> None:
        """Append awake spheres: one array per name of :data:`SPHERE_FIELDS`."""
        for f in SPHERE_FIELDS:
            setattr(self, f, np.concatenate([getattr(self, f), arrays[f]]))
        n = arrays["id"].shape[0]
        self.awake = np.concatenate([self.awake, np.ones(n, dtype=np.bool_)])
        self.rest = np.concatenate([self.rest, np.zeros(n)])

    def public(self, a: np.ndarray) -> np.ndarray:
        """A per-slot array reordered to id order (a copy)."""
        out = np.empty_like(a)
        out[self.id] = a
        return out

    def slots(self) -> np.ndarray:
        """Slot of every sphere id (N,) int64."""
        slot = np.empty(self.n, dtype=np.int64)
        slot[self.id] = np.arange(self.n)
        return slot
