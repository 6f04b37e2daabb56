"""Scenarios: the settled particle beds (``hill``, ``step``), the blade, and blade trajectories.

>>> from dozerlab.config import load_config
>>> from dozerlab.scenarios import build_bed, plan_trajectory
>>> cfg = load_config()
>>> bed = build_bed("hill", cfg)                       # doctest: +SKIP
>>> traj = plan_trajectory(bed, speed=1.0, depth=0.1, config=cfg)   # doctest: +SKIP
"""

from dozerlab.scenarios.bed import SCENARIOS, Bed
from dozerlab.scenarios.blade import (
    BladeGeometry,
    add_blade,
    centre_to_tip,
    start_tip,
    tip_to_centre,
)
from dozerlab.scenarios.build import build_bed, make_world
from dozerlab.scenarios.plots import plot_bed, plot_trajectory
from dozerlab.scenarios.trajectory import Trajectory, plan_trajectory

__all__ = [
    "SCENARIOS",
    "Bed",
    "BladeGeometry",
    "Trajectory",
    "add_blade",
    "build_bed",
    "centre_to_tip",
    "make_world",
    "plan_trajectory",
    "plot_bed",
    "plot_trajectory",
    "start_tip",
    "tip_to_centre",
]
