"""Scenarios: the settled particle beds (``hill``, ``step``), the blade, and blade trajectories.

Submodules: ``bed`` (``Bed``, ``SCENARIOS``), ``build`` (``build_bed``, ``make_world``), ``blade``,
``trajectory`` (``plan_trajectory``), ``heightfield`` and ``filters`` (the bed's surface),
``plots``, ``jobs`` (the ``bed`` and ``trajectory`` jobs), ``cli`` (the commands). Kept
import-light: the CLI imports this package to list its commands, so import what you use from its
submodule.

>>> from dozerlab.config import load_config
>>> from dozerlab.scenarios.build import build_bed
>>> from dozerlab.scenarios.trajectory import plan_trajectory
>>> cfg = load_config()
>>> bed = build_bed("hill", cfg)                       # doctest: +SKIP
>>> traj = plan_trajectory(bed, speed=1.0, depth=0.1, config=cfg)   # doctest: +SKIP
"""
