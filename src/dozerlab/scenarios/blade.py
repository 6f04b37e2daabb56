"""The bulldozer blade: a kinematic box whose reference point is its tip.

The blade spans ``blade.width`` along y, ``blade.height`` along z and ``blade.thickness`` along x.
Its **tip** is the centre of the lower edge of the front (+x) face; trajectories give tip
positions, torques are taken about the tip, and the sampling volume hangs off it. The box centre
is ``tip + (-thickness/2, 0, height/2)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from dozerlab.ndem import World
    from dozerlab.scenarios.bed import Bed


@dataclass(frozen=True)
class BladeGeometry:
    """Blade extents in m and the clearance ``start_gap`` (m) to the bed at the start."""

    width: float
    height: float
    thickness: float
    start_gap: float

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> BladeGeometry:
        """The ``blade`` section of a validated config."""
        b = config["blade"]
        return cls(
            float(b["width"]), float(b["height"]), float(b["thickness"]), float(b["start_gap"])
        )

    @property
    def half_extents(self) -> np.ndarray:
        """Box half extents (x, y, z) in m, shape (3,)."""
        return 0.5 * np.array([self.thickness, self.width, self.height])

    @property
    def tip_offset(self) -> np.ndarray:
        """centre − tip, shape (3,): (−thickness/2, 0, height/2)."""
        return np.array([-0.5 * self.thickness, 0.0, 0.5 * self.height])


def tip_to_centre(tip: np.ndarray, geometry: BladeGeometry) -> np.ndarray:
    """Box centre(s) from tip position(s); ``tip`` shape (3,) or (T, 3), m."""
    return np.asarray(tip, dtype=np.float64) + geometry.tip_offset


def centre_to_tip(centre: np.ndarray, geometry: BladeGeometry) -> np.ndarray:
    """Tip position(s) from box centre(s); ``centre`` shape (3,) or (T, 3), m."""
    return np.asarray(centre, dtype=np.float64) - geometry.tip_offset


def add_blade(world: World, tip: np.ndarray, config: dict[str, Any]) -> int:
    """Add the blade as a kinematic box with its tip at ``tip`` (3,) m; returns its body id.

    Its friction is ``material.wall_friction``. Drive it with ``world.set_velocity(id, v)``.
    """
    geometry = BladeGeometry.from_config(config)
    return world.add_box(
        tip_to_centre(tip, geometry),
        geometry.half_extents,
        kinematic=True,
        friction=float(config["material"]["wall_friction"]),
    )


def start_tip(bed: Bed, config: dict[str, Any]) -> np.ndarray:
    """The blade's start tip position (3,) in m, behind the bed.

    The front face is ``blade.start_gap`` behind the bed's start (x = 0, the start wall, or the
    rearmost particle surface if any lies behind it), at y = 0, with the lower edge level with
    the top of the bed's front face (the highest particle top within one particle diameter
    of the start; the ground if there is none).
    """
    geometry = BladeGeometry.from_config(config)
    x, z, r = bed.positions[:, 0], bed.positions[:, 2], bed.radii
    back = min(0.0, float((x - r).min())) if bed.count else 0.0
    front = x - r <= back + 2.0 * float(r.mean()) if bed.count else np.zeros(0, dtype=bool)
    top = float((z + r)[front].max()) if front.any() else 0.0
    return np.array([back - geometry.start_gap, 0.0, top])
