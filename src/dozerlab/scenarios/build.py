"""Building a scenario's bed the thesis's way (SPEC §3), and the world that holds it.

A thin emitter strip spanning the domain's width moves along x over the ground, creating
particles of radius r·(1 ± radius_dispersion) (uniform) at rest. Particles are created at a
constant rate and the strip moves slowly where the bed should be high: its speed is
``bed.emitter_speed · h_ref / h(x)``, with h(x) the scenario's target height profile and h_ref
its lowest height (at least a particle diameter), so the volume laid down per unit length
follows h(x) (equivalently, the strip sits where the cumulative target particle count reaches
the count emitted so far). Each particle is created ``bed.emitter_gap`` above the surface
beneath its random spot in the strip (never above a particle still falling), so it never
overlaps another and lands gently (a fall from higher up penetrates too far in one step at
the bed's dt); where the strip is busy, creation waits and so does the strip. The particles then settle
until the mean kinetic energy per particle falls below ``bed.settle_kinetic_energy``. The
build is deterministic for ``seed``.

The domain is held by static planes: the ground z = 0, side walls at y = ±width/2, a start wall
at x = 0 and an end wall at x = length. :func:`make_world` keeps all of them for the simulation:
the blade is kinematic and starts behind the start wall (x < 0), which the planes do not act on,
and cuts the bed's vertical start face; the trajectory ends ``trajectory.end_margin`` before the
end wall.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from dozerlab.ndem import World
from dozerlab.runtime import DozerlabError
from dozerlab.scenarios.bed import SCENARIOS, Bed

#: Emitter strip thickness along x, in mean particle radii.
STRIP_RADII = 8.0
#: Random spots tried per particle and step before creation waits for the next step.
ATTEMPTS = 8
#: Speed (m/s) below which a particle counts as landed: new particles may be created above it.
RESTING_SPEED = 0.15


def target_profile(scenario: str, config: dict[str, Any], x: np.ndarray) -> np.ndarray:
    """The scenario's target bed height (m) at positions ``x`` (m), shape of ``x``."""
    if scenario not in SCENARIOS:
        raise ValueError(f"scenario must be one of {list(SCENARIOS)}, got {scenario!r}")
    length = float(config["bed"]["length"])
    s = config["scenarios"][scenario]
    x = np.asarray(x, dtype=np.float64)
    if scenario == "hill":
        if s["peak_height"] <= s["base_height"]:
            raise ValueError(f"scenarios.hill.peak_height ({s['peak_height']}) must be > base_height "
                             f"({s['base_height']})")
        u = np.clip((x - s["center"] * length) / (s["half_width"] * length), -1.0, 1.0)
        return s["base_height"] + (s["peak_height"] - s["base_height"]) * np.cos(0.5 * np.pi * u) ** 2
    if s["high_height"] <= s["low_height"]:
        raise ValueError(f"scenarios.step.high_height ({s['high_height']}) must be > low_height "
                         f"({s['low_height']})")
    return np.where(x < s["edge"] * length, float(s["high_height"]), float(s["low_height"]))


def _add_walls(world: World, length: float, width: float, friction: float) -> dict[str, int]:
    planes = {
        "ground": ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
        "wall_start": ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)),
        "wall_end": ((length, 0.0, 0.0), (-1.0, 0.0, 0.0)),
        "wall_left": ((0.0, -0.5 * width, 0.0), (0.0, 1.0, 0.0)),
        "wall_right": ((0.0, 0.5 * width, 0.0), (0.0, -1.0, 0.0)),
    }
    return {name: world.add_plane(np.array(p), np.array(n), friction) for name, (p, n) in planes.items()}


def make_world(bed: Bed, config: dict[str, Any]) -> tuple[World, dict[str, int]]:
    """A simulation world (``World.from_config(config)``) holding ``bed``.

    It has the ground, the start/end and side walls (module docstring) and the bed's spheres with
    their velocities restored. Returns the world and the body ids by name: ``ground``,
    ``wall_start``, ``wall_end``, ``wall_left``, ``wall_right``.
    """
    world = World.from_config(config)
    ids = _add_walls(world, bed.length, bed.width, float(config["material"]["wall_friction"]))
    _add_particles(world, bed.positions, bed.radii, config, bed.velocities, bed.angular_velocities)
    return world, ids


def _add_particles(world: World, positions: np.ndarray, radii: np.ndarray, config: dict[str, Any],
                   velocities: np.ndarray | None = None, angular_velocities: np.ndarray | None = None) -> np.ndarray:
    m = config["material"]
    return world.add_spheres(positions, radii, m["density"], m["friction"], m["rolling_resistance"],
                             velocities=velocities, angular_velocities=angular_velocities)


def _kinetic_energy(world: World) -> float:
    """Mean translational + rotational kinetic energy per particle (J) of the world's spheres."""
    m, r = world.masses, world.radii
    if len(m) == 0:
        return 0.0
    v, w = world.velocities, world.angular_velocities
    e = 0.5 * m * np.einsum("ij,ij->i", v, v) + 0.2 * m * r * r * np.einsum("ij,ij->i", w, w)
    return float(e.mean())


class _Emitter:
    """The moving strip: where it is, and where it may place the next particles."""

    def __init__(self, scenario: str, config: dict[str, Any], rng: np.random.Generator):
        b = config["bed"]
        self.length, self.width = float(b["length"]), float(b["width"])
        self.r, self.spread, self.gap = float(b["radius"]), float(b["radius_dispersion"]), float(b["emitter_gap"])
        self.rng = rng
        x = np.linspace(0.0, self.length, 4097)
        h = target_profile(scenario, config, x)
        mean_volume = 4.0 / 3.0 * np.pi * self.r**3 * (1.0 + self.spread**2)
        per_length = float(b["packing_fraction"]) * self.width * h / mean_volume
        cumulative = np.concatenate([[0.0], np.cumsum(0.5 * (per_length[1:] + per_length[:-1]) * np.diff(x))])
        self.x, self.cumulative, self.total = x, cumulative, int(round(cumulative[-1]))
        h_ref = max(float(h.min()), 2.0 * self.r)
        self.rate = float(b["emitter_speed"]) * h_ref * per_length.max() / h.max()
        if self.total < 1:
            raise ValueError("the scenario's bed heights are too low to hold a single particle")

    def position(self, emitted: int) -> float:
        """Strip centre (m) once ``emitted`` particles have been created."""
        return float(np.interp(emitted + 0.5, self.cumulative, self.x))

    def place(self, n: int, xe: float, pos: np.ndarray, rad: np.ndarray,
              vel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Up to ``n`` new particles (positions (k, 3), radii (k,)) in the strip centred at ``xe``.

        Each goes to a random (x, y) in the strip, ``emitter_gap`` above the height at which it
        would first touch the ground, an existing particle (``pos``, ``rad``, velocities ``vel``)
        or one created just before it, so it never overlaps and falls only that gap. A spot above
        a particle still in motion is refused (the new one would follow it down and land fast);
        after ``ATTEMPTS`` refusals creation waits for the next step.
        """
        r_max = self.r * (1.0 + self.spread)
        half = 0.5 * STRIP_RADII * self.r
        lo, hi = max(xe - half, r_max), min(xe + half, self.length - r_max)
        near = np.abs(pos[:, 0] - xe) < half + 3.0 * r_max
        others_p, others_r = pos[near], rad[near]
        moving = np.linalg.norm(vel[near], axis=1) > RESTING_SPEED
        new_p: list[np.ndarray] = []
        new_r: list[float] = []
        for _ in range(n):
            radius = self.r * (1.0 + self.spread * self.rng.uniform(-1.0, 1.0))
            for _ in range(ATTEMPTS):
                c = np.array([self.rng.uniform(lo, hi),
                              self.rng.uniform(-0.5 * self.width + radius, 0.5 * self.width - radius), 0.0])
                reach2 = (others_r + radius) ** 2 - ((others_p[:, :2] - c[:2]) ** 2).sum(axis=1)
                under = reach2 > 0
                if (under & moving).any():
                    continue
                touch = others_p[under, 2] + np.sqrt(reach2[under])
                c[2] = max(radius, float(touch.max()) if touch.size else radius) + self.gap
                new_p.append(c)
                new_r.append(radius)
                # Later particles of this step must clear this one, which has not moved yet.
                others_p = np.vstack([others_p, c])
                others_r = np.append(others_r, radius)
                moving = np.append(moving, True)
                break
            else:
                break
        return np.array(new_p).reshape(-1, 3), np.array(new_r)


def build_bed(scenario: str, config: dict[str, Any], *, progress: bool = True) -> Bed:
    """Build and settle the bed of ``scenario`` (``hill`` or ``step``) from a validated config.

    Uses ``bed.dt`` and ``bed.iterations`` for the solver, the ``solver`` section's gravity,
    damping and overlap limit, ``material`` and ``seed``. Raises DozerlabError if the bed has not
    settled within ``bed.max_settle_time`` simulated seconds or a particle left the domain.
    """
    from tqdm import tqdm

    b, solver, mat = config["bed"], config["solver"], config["material"]
    emitter = _Emitter(scenario, config, np.random.default_rng(int(config["seed"])))
    dt, log_every = float(b["dt"]), int(b["log_every"])
    world = World(
        dt, int(b["iterations"]), solver["gravity"], damping_steps=solver["damping_steps"],
        youngs_modulus=mat["youngs_modulus"], poisson_ratio=mat["poisson_ratio"],
        max_overlap=solver["max_overlap"],
    )
    _add_walls(world, emitter.length, emitter.width, float(mat["wall_friction"]))
    max_steps = int(np.ceil(float(b["max_settle_time"]) / dt))
    threshold = float(b["settle_kinetic_energy"])
    log_t: list[float] = []
    log_e: list[float] = []
    log_c: list[int] = []
    emitted, backlog, energy, emission_time = 0, 0.0, np.inf, np.nan
    start = time.perf_counter()
    bar = tqdm(total=max_steps, desc=f"bed {scenario}", unit="step", disable=not progress, file=None)
    step = 0
    try:
        while step < max_steps:
            if emitted < emitter.total:
                backlog = min(backlog + emitter.rate * dt, float(emitter.total - emitted))
                if int(backlog):
                    new_p, new_r = emitter.place(int(backlog), emitter.position(emitted), world.positions,
                                                 world.radii, world.velocities)
                    if len(new_r):
                        _add_particles(world, new_p, new_r, config)
                        emitted += len(new_r)
                        backlog -= len(new_r)
                if emitted == emitter.total:
                    emission_time = (step + 1) * dt
            stats = world.step(1)
            step += 1
            energy = _kinetic_energy(world)
            if step % log_every == 0:
                log_t.append(step * dt)
                log_e.append(energy)
                log_c.append(int(stats.contacts))
                bar.set_postfix(particles=emitted, ke=f"{energy:.2e}", refresh=False)
            bar.update(1)
            if emitted == emitter.total and energy < threshold:
                break
    finally:
        bar.close()
    if emitted < emitter.total or energy >= threshold:
        raise DozerlabError(
            f"bed {scenario} did not settle within bed.max_settle_time = {b['max_settle_time']} s "
            f"({emitted}/{emitter.total} particles created, kinetic energy per particle {energy:.3g} J "
            f"> bed.settle_kinetic_energy {threshold:g} J); raise max_settle_time or emitter_speed")
    bed = Bed(
        scenario=scenario, length=emitter.length, width=emitter.width,
        positions=world.positions.copy(), radii=world.radii.copy(), masses=world.masses.copy(),
        velocities=world.velocities.copy(), angular_velocities=world.angular_velocities.copy(),
        material=dict(mat), seed=int(config["seed"]),
        settle_time=np.array(log_t), settle_kinetic_energy=np.array(log_e), settle_contacts=np.array(log_c),
        info={"time": step * dt, "steps": step, "emission_time": emission_time,
              "wall_time": time.perf_counter() - start, "dt": dt, "iterations": int(b["iterations"]),
              "bed": dict(b), "shape": dict(config["scenarios"][scenario])},
    )
    _check_inside(bed)
    return bed


def _check_inside(bed: Bed) -> None:
    """Raise DozerlabError if a particle centre lies outside the walled domain (a blown-up build)."""
    p, slack = bed.positions, 0.5 * bed.radii
    outside = (
        (p[:, 0] < -slack) | (p[:, 0] > bed.length + slack)
        | (np.abs(p[:, 1]) > 0.5 * bed.width + slack) | (p[:, 2] < -slack)
    )
    if outside.any():
        raise DozerlabError(f"bed {bed.scenario}: {int(outside.sum())} particles left the domain while settling")
