"""Field sampling (docs/data.md): a grid of bins attached to the blade and particle–bin weights.

The sampling volume is a box in the blade frame (origin at the tip, axes as the world's, the blade
only translates): x ∈ [0, length] in front of the front face and ``behind_bins`` more bins
behind it, y across the blade's width and ``side_bins`` more bins beyond each of its ends, z from
``below_edge`` below the lower edge up to the blade's top and ``above_bins`` more bins over it.
It holds (Nx, Ny, Nz) bins, of which the **blade part** — the bins in front of the face, across
the blade's width, up to its top — is what pushes on the blade (the force models read only it);
the others hold the windrows the blade heaps beside it and their slumping into its cut behind
it, which the reduced simulation moves grains with.

Particle–bin weight (thesis algorithm 1): the fraction of the particle's axis-aligned bounding box
inside the bin, w = d_x d_y d_z / (2r)³ with d the per-axis overlap of the intervals
[p − r, p + r] and [b − l/2, b + l/2]. For 2r ≤ l this is exactly the thesis's
clamp(r + l/2 − |p − b|, 0, 2r); clamping to min(2r, l) instead keeps the weights of a particle
wholly inside the volume summing to 1 also when particles are wider than bins (the default config's
0.1 m particles in 0.05 m bins).

Bin velocity is the weight-normalised mean Σ w v / Σ w (thesis eq. 3.1 divides by the particle
count, which makes a bin's velocity depend on how many particles merely touch it); empty bins
have zero velocity. Bin density is ρ = Σ w m / V_bin, so Σ ρ V_bin is the mass inside the volume.

The kernel loops once over the particles and touches only the bins each bounding box overlaps,
after a cheap test that skips particles outside the volume; it is serial (deterministic sums, and
one pass over particles costs little next to a solver step's many sweeps over contacts).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

_MAX_SPAN = 64  # most bins one particle's bounding box may span per axis


@numba.njit(cache=True)
def _accumulate(positions, velocities, radii, masses, lower, size, bins, wsum, wvel, wmass):
    """Add every particle's weighted contribution to the bins its bounding box overlaps.

    positions (N, 3), velocities (a tuple of K arrays (N, 3): K velocities of each particle,
    accumulated in one pass into C = 3·K channels) and radii, masses (N,) are world-frame
    float64;
    ``lower`` (3,) is the volume's minimum corner in the world frame, ``size`` (3,) the bin
    size, ``bins`` (3,) the counts. Accumulators: wsum (Nx,Ny,Nz) Σw, wvel (Nx,Ny,Nz,C) Σwv,
    wmass (Nx,Ny,Nz) Σwm.
    """
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    ov = np.zeros((3, _MAX_SPAN))  # per-axis overlap fraction with each touched bin
    nk = len(velocities)
    for p in range(positions.shape[0]):
        r = radii[p]
        outside = False
        for a in range(3):
            q = positions[p, a] - lower[a]
            extent = bins[a] * size[a]
            if q + r <= 0.0 or q - r >= extent:
                outside = True
                break
            i0 = max(int(np.floor((q - r) / size[a])), 0)
            i1 = min(int(np.floor((q + r) / size[a])), bins[a] - 1)
            lo[a] = i0
            hi[a] = i1
            for i in range(i0, i1 + 1):
                b0 = i * size[a]
                d = min(q + r, b0 + size[a]) - max(q - r, b0)
                ov[a, i - i0] = max(d, 0.0) / (2.0 * r)
        if outside:
            continue
        m = masses[p]
        for i in range(lo[0], hi[0] + 1):
            wx = ov[0, i - lo[0]]
            for j in range(lo[1], hi[1] + 1):
                wxy = wx * ov[1, j - lo[1]]
                for k in range(lo[2], hi[2] + 1):
                    w = wxy * ov[2, k - lo[2]]
                    if w <= 0.0:
                        continue
                    wsum[i, j, k] += w
                    for kk in range(nk):
                        v = velocities[kk]
                        for a in range(3):
                            wvel[i, j, k, 3 * kk + a] += w * v[p, a]
                    wmass[i, j, k] += w * m


@numba.njit(cache=True)
def _finish(wsum, wvel, wmass, inv_volume, velocity, density):
    """velocity = Σwv/Σw (0 where Σw = 0) and density = Σwm / V_bin, into float32 outputs
    (velocity and wvel (Nx,Ny,Nz,C))."""
    nx, ny, nz = wsum.shape
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                w = wsum[i, j, k]
                for a in range(wvel.shape[3]):
                    velocity[i, j, k, a] = wvel[i, j, k, a] / w if w > 0.0 else 0.0
                density[i, j, k] = wmass[i, j, k] * inv_volume


@dataclass(frozen=True)
class SamplingGrid:
    """The bins of the sampling volume, in the blade frame (origin at the tip).

    Attributes:
        bins: (Nx, Ny, Nz) bin counts.
        bin_size: (3,) bin edge lengths, m.
        lower: (3,) minimum corner of the volume relative to the tip, m.
        behind_bins: bins behind the blade's face (x), outside the blade part.
        side_bins: bins beyond each end of the blade (y), outside the blade part.
        above_bins: bins over the blade's top (z), outside the blade part.
    """

    bins: tuple[int, int, int]
    bin_size: tuple[float, float, float]
    lower: tuple[float, float, float]
    behind_bins: int = 0
    side_bins: int = 0
    above_bins: int = 0

    def __post_init__(self) -> None:
        if len(self.bins) != 3 or min(self.bins) < 1:
            raise ValueError(f"sampling bins must be three counts >= 1, got {self.bins}")
        if len(self.bin_size) != 3 or min(self.bin_size) <= 0:
            raise ValueError(f"sampling bin_size must be three lengths > 0, got {self.bin_size}")
        if not (
            0 <= self.behind_bins < self.bins[0]
            and 0 <= 2 * self.side_bins < self.bins[1]
            and 0 <= self.above_bins < self.bins[2]
        ):
            raise ValueError(
                f"behind_bins {self.behind_bins}, side_bins {self.side_bins} and above_bins "
                f"{self.above_bins} must leave a blade part in the {self.bins} bins"
            )

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> SamplingGrid:
        """The grid of a validated config's ``sampling`` and ``blade`` sections:
        ``sampling.bins`` are the blade part's counts, the behind, side and above bins are added."""
        s, b = config["sampling"], config["blade"]
        nx, ny, nz = (int(n) for n in s["bins"])
        behind, side, above = (int(s[k]) for k in ("behind_bins", "side_bins", "above_bins"))
        height = b["height"] + s["below_edge"]
        dx, dy = s["length"] / nx, b["width"] / ny
        return cls(
            bins=(nx + behind, ny + 2 * side, nz + above),
            bin_size=(dx, dy, height / nz),
            lower=(-behind * dx, -b["width"] / 2 - side * dy, -s["below_edge"]),
            behind_bins=behind,
            side_bins=side,
            above_bins=above,
        )

    @property
    def blade_part(self) -> tuple[int, int, int, int]:
        """(x0, y0, y1, z1): the blade part is bins [x0:, y0:y1, :z1] of the grid."""
        return (
            self.behind_bins,
            self.side_bins,
            self.bins[1] - self.side_bins,
            self.bins[2] - self.above_bins,
        )

    def attrs(self) -> dict[str, list[int] | list[float]]:
        """The grid's entries in a field store's attributes (docs/data.md)."""
        return {
            "bins": list(self.bins),
            "bin_size": list(self.bin_size),
            "blade_part": list(self.blade_part),
        }

    @property
    def bin_volume(self) -> float:
        """Volume of one bin, m³."""
        return float(np.prod(self.bin_size))

    def centres(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bin-centre coordinates (x (Nx,), y (Ny,), z (Nz,)) in the blade frame, m."""
        x, y, z = (
            lo + (np.arange(n) + 0.5) * size
            for lo, n, size in zip(self.lower, self.bins, self.bin_size, strict=True)
        )
        return x, y, z

    def _sums(
        self,
        particles: tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray, np.ndarray],
        tip: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Σw (Nx, Ny, Nz), Σw·v (Nx, Ny, Nz, 3K) and Σw·m (Nx, Ny, Nz) of the particles'
        algorithm-1 weights w per bin (:func:`_accumulate`); ``particles`` are the arguments of
        :meth:`sample` before ``tip``, with a tuple of K velocities: positions, (velocities (N,
        3), …), radii, masses."""
        positions, radii, masses = (
            np.ascontiguousarray(particles[i], dtype=np.float64) for i in (0, 2, 3)
        )
        velocities = tuple(np.ascontiguousarray(v, dtype=np.float64) for v in particles[1])
        n = positions.shape[0]
        if (
            positions.shape != (n, 3)
            or not velocities
            or any(v.shape != (n, 3) for v in velocities)
            or radii.shape != (n,)
            or masses.shape != (n,)
        ):
            raise ValueError(
                "positions must be (N, 3) as the velocities, radii/masses (N,), got "
                f"{positions.shape}, {[v.shape for v in velocities]}, {radii.shape}, "
                f"{masses.shape}"
            )
        if n and radii.min() <= 0:
            raise ValueError("particle radii must be > 0")
        if n and 2 * radii.max() / min(self.bin_size) > _MAX_SPAN - 2:
            raise ValueError(
                f"particles span more than {_MAX_SPAN - 2} bins; use fewer, larger bins"
            )
        wsum = np.zeros(self.bins)
        wvel = np.zeros((*self.bins, 3 * len(velocities)))
        wmass = np.zeros(self.bins)
        lower = np.asarray(tip, dtype=np.float64) + np.asarray(self.lower)
        _accumulate(
            positions,
            velocities,
            radii,
            masses,
            lower,
            np.asarray(self.bin_size, dtype=np.float64),
            np.asarray(self.bins, dtype=np.int64),
            wsum,
            wvel,
            wmass,
        )
        return wsum, wvel, wmass

    def weights(self, positions: np.ndarray, radii: np.ndarray, tip: np.ndarray) -> np.ndarray:
        """Σ of the particles' algorithm-1 weights per bin, (Nx, Ny, Nz); for one particle, its weights.

        positions (N, 3) and the blade ``tip`` (3,) in the world frame, m; radii (N,), m.
        """
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        n = positions.shape[0]
        wsum, _, _ = self._sums(
            (positions, (np.zeros((n, 3)),), np.asarray(radii).reshape(n), np.ones(n)), tip
        )
        return wsum

    def sample(
        self,
        positions: np.ndarray,
        velocities: np.ndarray,
        radii: np.ndarray,
        masses: np.ndarray,
        tip: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Sample the fields at the blade's ``tip`` (3,), world frame, m.

        Args:
            positions, velocities: particles (N, 3), m and m/s, world frame.
            radii, masses: (N,), m and kg.
            tip: the blade tip (3,), m.

        Returns:
            velocity (Nx, Ny, Nz, 3) float32, m/s (Σwv/Σw, 0 in empty bins) and
            density (Nx, Ny, Nz) float32, kg/m³ (Σwm / V_bin).
        """
        wsum, wvel, wmass = self._sums((positions, (velocities,), radii, masses), tip)
        velocity = np.empty(wvel.shape, dtype=np.float32)
        density = np.empty(wsum.shape, dtype=np.float32)
        _finish(wsum, wvel, wmass, 1.0 / self.bin_volume, velocity, density)
        return velocity, density

    def sample_velocities(
        self,
        positions: np.ndarray,
        velocities: tuple[np.ndarray, ...],
        radii: np.ndarray,
        masses: np.ndarray,
        tip: np.ndarray,
    ) -> tuple[list[np.ndarray], np.ndarray]:
        """:meth:`sample` of several velocities of the same particles in one pass over them.

        ``velocities``: K arrays (N, 3), m/s. Returns the K velocity fields (Nx, Ny, Nz, 3)
        float32, each bit for bit what :meth:`sample` gives for it, and the density
        (Nx, Ny, Nz) float32, kg/m³.
        """
        wsum, wvel, wmass = self._sums((positions, velocities, radii, masses), tip)
        velocity = np.empty(wvel.shape, dtype=np.float32)
        density = np.empty(wsum.shape, dtype=np.float32)
        _finish(wsum, wvel, wmass, 1.0 / self.bin_volume, velocity, density)
        return [velocity[..., 3 * i : 3 * i + 3] for i in range(len(velocities))], density
