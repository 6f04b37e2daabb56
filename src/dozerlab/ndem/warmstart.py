"""Warm start: the previous step's multipliers of contacts that persist.

Contacts are keyed by the sphere ids (stable across the spatial re-sort) and the body id. The
vector multipliers are stored as acting on the lower-id sphere, so a pair whose slots swap
between steps is matched with the right sign.
"""

from __future__ import annotations

import numpy as np

ID_BITS = 23  # sphere ids and bodies below 2**23 each


def contact_keys(ids: np.ndarray, ci: np.ndarray, cj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """int64 keys (Nc,) and the sign (Nc,) turning the stored orientation into this one."""
    a = ids[ci]
    body = cj < 0
    b = np.where(body, (1 << ID_BITS) + cj, ids[np.where(body, 0, cj)])  # body k → 2**23 - 1 - k
    lo = np.where(body, a, np.minimum(a, b))
    hi = np.where(body, b, np.maximum(a, b))
    sign = np.where(body | (a < b), 1.0, -1.0)
    return (lo << ID_BITS) | hi, sign


class WarmStart:
    """Multipliers of the last step, sorted by contact key."""

    def __init__(self) -> None:
        self.keys = np.zeros(0, dtype=np.int64)
        self.lam = np.zeros((0, 7))

    def lookup(self, ids: np.ndarray, ci: np.ndarray, cj: np.ndarray,
               normals: np.ndarray) -> tuple[np.ndarray, int]:
        """Initial multipliers (Nc, 7) for this step's contacts and how many persisted.

        The friction and rolling vectors are projected onto the new tangent plane.
        """
        keys, sign = contact_keys(ids, ci, cj)
        lam = np.zeros((ci.shape[0], 7))
        if self.keys.size == 0 or keys.size == 0:
            return lam, 0
        pos = np.minimum(np.searchsorted(self.keys, keys), self.keys.size - 1)
        hit = self.keys[pos] == keys
        lam[hit] = self.lam[pos[hit]]
        lam[:, 1:] *= sign[:, None]
        for s in (slice(1, 4), slice(4, 7)):
            lam[:, s] -= np.einsum("ij,ij->i", lam[:, s], normals)[:, None] * normals
        return lam, int(hit.sum())

    def store(self, ids: np.ndarray, ci: np.ndarray, cj: np.ndarray, lam: np.ndarray) -> None:
        """Remember this step's multipliers."""
        keys, sign = contact_keys(ids, ci, cj)
        order = np.argsort(keys, kind="stable")
        self.keys = keys[order]
        self.lam = lam[order].copy()
        self.lam[:, 1:] *= sign[order, None]
