"""Transport of the fields by their own velocity, in the blade's frame: the physics every
learned evolution model starts from.

The grid is attached to the blade, so between rows it moves by the blade velocity times the
row interval: ≈0.2 bin per row at 1 m/s on the default grid. Material at rest in the world
therefore streams backwards through the grid while the pile pushed by the blade stays put. One
conservative upwind (donor-cell) step of the mass ρ and momentum ρv along the velocity relative
to the blade, u = v − v_blade, makes that frame shift explicit and keeps the mass in the volume
exactly, but for what crosses its faces; material enters through the front face with the
values of the front bins (nothing beyond the volume is known).
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

#: Bins lighter than this (kg/m³; a grain per bin is ~1000) count as empty: zero velocity.
EMPTY_DENSITY = 1.0


def frame_shift(
    blade_velocity: torch.Tensor, row_dt: float, bin_size: tuple[float, float, float]
) -> torch.Tensor:
    """How far the grid moves between rows, in bins per axis: v_blade·Δt / bin size (…, 3)."""
    h = torch.tensor(bin_size, dtype=blade_velocity.dtype, device=blade_velocity.device)
    return blade_velocity * (row_dt / h)


def _face_flux(q: torch.Tensor, rho: torch.Tensor, u: torch.Tensor, axis: int) -> torch.Tensor:
    """Upwind flux of the conserved channels q (B, C, X, Y, Z) through every face along
    ``axis`` (2, 3 or 4), the volume's two outer faces included (replicated ghost bins):
    (B, C, …, n + 1, …) in units of q times bins per row. The face velocity is the
    mass-weighted mean of its two bins', so an empty bin does not drag material with it."""
    pad = [0, 0, 0, 0, 0, 0]
    pad[2 * (4 - axis)], pad[2 * (4 - axis) + 1] = 1, 1
    qp = F.pad(q, pad, mode="replicate")
    rp = F.pad(rho, pad, mode="replicate")
    up = F.pad(u, pad, mode="replicate")
    n = qp.shape[axis]
    lo, hi = (slice(None),) * axis + (slice(0, n - 1),), (slice(None),) * axis + (slice(1, n),)
    m = rp[lo] + rp[hi]
    uf = torch.where(
        m > 0, (rp[lo] * up[lo] + rp[hi] * up[hi]) / m.clamp_min(1e-30), 0.5 * (up[lo] + up[hi])
    )
    return uf.clamp_min(0) * qp[lo] + uf.clamp_max(0) * qp[hi]


def advect(
    density: torch.Tensor,
    velocity: torch.Tensor,
    blade_velocity: torch.Tensor,
    row_dt: float,
    bin_size: tuple[float, float, float],
) -> tuple[torch.Tensor, torch.Tensor]:
    """One row ahead: density (B, X, Y, Z) kg/m³ and world-frame velocity (B, X, Y, Z, 3) m/s
    carried along v − ``blade_velocity`` (B, 3), the blade velocity of the step being made.

    Mass and momentum are moved between bins by upwind fluxes; the new velocity is momentum over
    mass (zero in bins lighter than :data:`EMPTY_DENSITY`). Differentiable (the neural model
    trains through it)."""
    shift = frame_shift(blade_velocity, row_dt, bin_size)  # B, 3 bins per row
    h = torch.tensor(bin_size, dtype=velocity.dtype, device=velocity.device)
    u = (velocity * (row_dt / h) - shift[:, None, None, None, :]).permute(
        0, 4, 1, 2, 3
    )  # B,3,X,Y,Z
    rho = density.unsqueeze(1)
    q = torch.cat([rho, rho * velocity.permute(0, 4, 1, 2, 3)], dim=1)  # B, 4, X, Y, Z
    new = q
    for a in range(3):
        flux = _face_flux(q, rho, u[:, a : a + 1], 2 + a)
        n = flux.shape[2 + a]
        lo = (slice(None),) * (2 + a) + (slice(0, n - 1),)
        hi = (slice(None),) * (2 + a) + (slice(1, n),)
        new = new - (flux[hi] - flux[lo])
    rho_new = new[:, 0].clamp_min(0)
    full = rho_new > EMPTY_DENSITY
    v_new = torch.where(
        full[:, None],
        new[:, 1:] / rho_new.clamp_min(EMPTY_DENSITY)[:, None],
        torch.zeros_like(new[:, 1:]),
    )
    return rho_new, v_new.permute(0, 2, 3, 4, 1)
