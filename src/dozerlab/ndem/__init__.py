"""The non-smooth DEM engine: spheres, planes, static and kinematic boxes; SPOOK + PGS.

>>> from dozerlab.ndem import World
>>> w = World(dt=0.01, iterations=50)
>>> ground = w.add_plane(point=(0, 0, 0), normal=(0, 0, 1))
>>> ids = w.add_spheres([[0.0, 0.0, 0.05]], radius=0.05)
>>> stats = w.step(10)
"""

from dozerlab.ndem.stats import DivergenceError, StepStats
from dozerlab.ndem.world import World

__all__ = ["DivergenceError", "StepStats", "World"]
