"""What a step reports, and the error a diverging simulation raises."""

from __future__ import annotations

from dataclasses import dataclass

from dozerlab.runtime import DozerlabError


class DivergenceError(DozerlabError, RuntimeError):
    """The simulation blew up: a non-finite state or an overlap beyond ``max_overlap``."""


@dataclass(frozen=True)
class StepStats:
    """Summary of one step.

    contacts: touching contacts (overlap > 0); speculative: near contacts (a gap smaller than
    the contact margin) also handed to the solver (with ``solver.active_zone``, both count only
    the contacts of awake spheres, the ones the step solves); residual: RMS of the normal rows' last PGS
    update, in m/s (→ 0 as the solver converges); max_overlap: largest overlap in m and
    max_overlap_fraction the largest overlap over the smaller radius, at the start of the step;
    step and time (s) after the step; iterations: solver sweeps run (at most
    ``solver.iterations``, fewer when ``solver.tolerance`` stopped the solve, and up to that
    many more per ``solver.relinearize`` round that ran); active: spheres
    awake after the step (all of them unless ``solver.active_zone`` is enabled); rounds: the
    ``solver.relinearize`` rounds that ran (0 in a step ``solver.relinearize_above`` passed
    over).
    """

    step: int
    time: float
    contacts: int
    speculative: int
    residual: float
    max_overlap: float
    max_overlap_fraction: float
    iterations: int = 0
    active: int = 0
    rounds: int = 0
