"""Adaptive sweeps: an initial design, then rounds of NDEM runs picked where an ensemble
disagrees most (:mod:`~dozerlab.adaptive.design`), and the learning curve that measures them
against the grid and random designs (:mod:`~dozerlab.adaptive.curve`)."""
