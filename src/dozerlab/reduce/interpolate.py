"""Grid → particles: trilinear interpolation of a sampled field at particle positions.

The field lives at the bin centres of a :class:`~dozerlab.fields.sampling.SamplingGrid` placed
at the blade tip. A point between centres takes the trilinear blend of its 8 neighbours; a point
within half a bin of the volume's boundary takes the nearest centre's value along that axis
(constant extrapolation), so nothing is invented outside the sampled data.

With a ``weight`` field (the density) the blend is mass-weighted, Σ c ρ v / Σ c ρ with c the
trilinear coefficients: the bed's surface lies inside bins, and a plain blend with the empty
bins above it (velocity 0 by the store's convention) would slow the grains at the surface.
Blending differences from one corner's value makes a uniform field come back exactly (bit for
bit) either way, and a linear one to round-off where the weight is uniform.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _axis(q: float, size: float, n: int) -> tuple[int, int, float]:
    """Neighbour indices (i0, i1) and the weight of i1 along one axis; ``q`` from the lower corner."""
    s = q / size - 0.5  # in units of bins, 0 at the first centre
    if s <= 0.0:
        return 0, 0, 0.0
    if s >= n - 1:
        return n - 1, n - 1, 0.0
    i0 = int(np.floor(s))
    return i0, i0 + 1, s - i0


@njit(cache=True)
def trilinear(field, weight, lower, size, points, out):  # pragma: no cover - compiled
    """Interpolate ``field`` (Nx,Ny,Nz,3) at ``points`` (P,3) into ``out`` (P,3).

    ``lower`` (3,) is the volume's minimum corner in the points' frame, ``size`` (3,) the bin
    size (m); ``weight`` (Nx,Ny,Nz) non-negative, or an empty (0,0,0) array for a plain blend.
    A point whose neighbours all have zero weight gets the plain blend. Three channels, each
    blend's sums in registers (the loop's velocity fields; :func:`interpolate` takes any
    count): with them in two small arrays over the channels, the blend of a step's carried
    grains took 0.18-0.20 ms against 0.12 (BENCHMARKS.md, "The loop's passes over the grains,
    lighter").
    """
    nx, ny, nz, _ = field.shape
    weighted = weight.size > 0
    for p in range(points.shape[0]):
        i0, i1, fx = _axis(points[p, 0] - lower[0], size[0], nx)
        j0, j1, fy = _axis(points[p, 1] - lower[1], size[1], ny)
        k0, k1, fz = _axis(points[p, 2] - lower[2], size[2], nz)
        f0, f1, f2 = field[i0, j0, k0, 0], field[i0, j0, k0, 1], field[i0, j0, k0, 2]
        a0 = a1 = a2 = 0.0
        p0 = p1 = p2 = 0.0
        wsum = 0.0
        for corner in range(8):
            i = i1 if corner & 4 else i0
            j = j1 if corner & 2 else j0
            k = k1 if corner & 1 else k0
            cx = fx if corner & 4 else 1.0 - fx
            cy = fy if corner & 2 else 1.0 - fy
            cz = fz if corner & 1 else 1.0 - fz
            coef = cx * cy * cz
            if coef == 0.0:
                continue
            wc = coef * weight[i, j, k] if weighted else 0.0
            wsum += wc
            d0 = field[i, j, k, 0] - f0
            d1 = field[i, j, k, 1] - f1
            d2 = field[i, j, k, 2] - f2
            p0 += coef * d0
            p1 += coef * d1
            p2 += coef * d2
            a0 += wc * d0
            a1 += wc * d1
            a2 += wc * d2
        if wsum > 0.0:
            out[p, 0], out[p, 1], out[p, 2] = f0 + a0 / wsum, f1 + a1 / wsum, f2 + a2 / wsum
        else:
            out[p, 0], out[p, 1], out[p, 2] = f0 + p0, f1 + p1, f2 + p2


def interpolate(
    field: np.ndarray,
    points: np.ndarray,
    lower: np.ndarray,
    bin_size: np.ndarray,
    weight: np.ndarray | None = None,
) -> np.ndarray:
    """The field at ``points``: (P, C) float64, or (P,) for a scalar field.

    Args:
        field: (Nx, Ny, Nz, C) or (Nx, Ny, Nz) values at the bin centres.
        points: (P, 3) positions, m, in the same frame as ``lower``.
        lower: (3,) the volume's minimum corner, m.
        bin_size: (3,) bin edge lengths, m.
        weight: optional (Nx, Ny, Nz) non-negative weights (the density) for a mass-weighted blend.
    """
    f = np.asarray(field, dtype=np.float64)
    scalar = f.ndim == 3
    if scalar:
        f = f[..., None]
    if f.ndim != 4:
        raise ValueError(f"field must be (Nx, Ny, Nz[, C]), got shape {np.shape(field)}")
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    w = np.empty((0, 0, 0)) if weight is None else np.ascontiguousarray(weight, dtype=np.float64)
    if weight is not None and w.shape != f.shape[:3]:
        raise ValueError(f"weight must have shape {f.shape[:3]}, got {w.shape}")
    channels = f.shape[3]
    # three channels a blend, the last group padded with zeros (each channel is blended alone)
    groups = -(-channels // 3)
    if channels < 3 * groups:
        f = np.concatenate([f, np.zeros((*f.shape[:3], 3 * groups - channels))], axis=3)
    out = np.empty((pts.shape[0], 3 * groups))
    lo, size = np.asarray(lower, dtype=np.float64), np.asarray(bin_size, dtype=np.float64)
    for g in range(groups):
        part = out if groups == 1 else np.empty((pts.shape[0], 3))
        trilinear(np.ascontiguousarray(f[..., 3 * g : 3 * g + 3]), w, lo, size, pts, part)
        out[:, 3 * g : 3 * g + 3] = part
    return out[:, 0] if scalar else out[:, :channels]
