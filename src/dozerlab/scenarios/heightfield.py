"""The bed's height field (docs/physics.md, path step 1): highest particle surface per ground subdivision.

Collapsing it along y (thesis eq. 3.4) is ``h.mean(axis=1)``.

The ground rectangle x ∈ [0, length], y ∈ [-width/2, width/2] is divided into (Nx, Ny) cells.
A cell's height is the highest point of any particle above the cell's centre: a sphere of
centre (px, py, pz) and radius r covering the centre (cx, cy) contributes
``pz + sqrt(r² - (cx-px)² - (cy-py)²)``, its top ``pz + r`` when it sits right above it. The
thesis took the top of the particles whose centre falls in the cell; with cells narrower than a
particle (the default 1 cm) most cells would then stay empty, so the covering sphere's surface
is the faithful reading of "max particle top per subdivision". Cells no particle covers have
height 0 (the ground).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _height_field(pos, radii, x0, y0, dx, dy, nx, ny):  # pragma: no cover - compiled
    h = np.zeros((nx, ny))
    for p in range(pos.shape[0]):
        r = radii[p]
        px, py, pz = pos[p, 0], pos[p, 1], pos[p, 2]
        i0 = max(int(np.ceil((px - r - x0) / dx - 0.5)), 0)
        i1 = min(int(np.floor((px + r - x0) / dx - 0.5)), nx - 1)
        j0 = max(int(np.ceil((py - r - y0) / dy - 0.5)), 0)
        j1 = min(int(np.floor((py + r - y0) / dy - 0.5)), ny - 1)
        for i in range(i0, i1 + 1):
            ddx = x0 + (i + 0.5) * dx - px
            for j in range(j0, j1 + 1):
                ddy = y0 + (j + 0.5) * dy - py
                q = r * r - ddx * ddx - ddy * ddy
                if q >= 0.0:
                    top = pz + np.sqrt(q)
                    if top > h[i, j]:
                        h[i, j] = top
    return h


def height_field(
    positions: np.ndarray,
    radii: np.ndarray,
    length: float,
    width: float,
    subdivisions: tuple[int, int] | list[int],
) -> tuple[np.ndarray, np.ndarray]:
    """Height field h(x, y) of spheres over the bed's ground rectangle.

    ``positions`` (N, 3) and ``radii`` (N,) in m; ``subdivisions`` = (Nx, Ny). Returns the cell
    centres along x, shape (Nx,), and the heights in m, shape (Nx, Ny).
    """
    nx, ny = (int(n) for n in subdivisions)
    if nx < 1 or ny < 1:
        raise ValueError(
            f"trajectory.subdivisions must be >= 1 in both directions, got {subdivisions}"
        )
    if length <= 0 or width <= 0:
        raise ValueError(f"bed length and width must be > 0 m, got {length}, {width}")
    pos = np.ascontiguousarray(positions, dtype=np.float64).reshape(-1, 3)
    rad = np.ascontiguousarray(radii, dtype=np.float64).reshape(-1)
    dx, dy = length / nx, width / ny
    h = _height_field(pos, rad, 0.0, -width / 2, dx, dy, nx, ny)
    return (np.arange(nx) + 0.5) * dx, h
