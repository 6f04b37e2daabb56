"""Building a scenario's bed the thesis's way (docs/physics.md), and the world that holds it.

A thin emitter strip spanning the domain's width makes one pass along x over the ground,
creating layers of particles of radius r·(1 ± radius_dispersion) (uniform), each at a random
spot of its cell of a grid across the strip, a small gap above the local surface and falling
at ``bed.emitter_drop_speed`` (impacts are inelastic). The strip lingers where the bed should be
high: it lays particles in the cells that hold fewer than ``packing_fraction`` × the target
volume above them (the scenario's target height h(x, y) at the cell's centre × cell area,
:func:`dozerlab.terrain.target_height`: a preset, a profile or a heightmap) and moves on one row
once its rear row holds its share, so the volume laid per cell follows h(x, y), and material that rolls
ahead of the strip is not laid again. The particles then settle until the mean kinetic energy
per particle falls below ``bed.settle_kinetic_energy``; slopes steeper than the pile stands
slump to its angle of repose. The build is deterministic for ``seed``.

The domain is held by static planes: the ground z = 0, side walls at y = ±width/2, a start wall
at x = 0 and an end wall at x = length. :func:`make_world` keeps all of them for the simulation:
the blade is kinematic and starts behind the start wall (x < 0), which the planes do not act on,
and cuts the bed's vertical start face; the trajectory ends ``trajectory.end_margin`` before the
end wall.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from dozerlab.config import height_bound
from dozerlab.integrity import sha256_file
from dozerlab.ndem import World
from dozerlab.runtime import DozerlabError
from dozerlab.scenarios.bed import Bed
from dozerlab.terrain import check_terrain, heightmap_file, target_height

log = logging.getLogger(__name__)
#: Solver steps between the log lines of a bed build (1 s simulated at the default dt).
LOG_LINE_STEPS = 100

#: Rows of particles (along x) in one emitted layer: the strip's thickness.
STRIP_ROWS = 2
#: Extra width of a layer cell beyond a largest particle's diameter, in mean radii: room for
#: each particle's random offset inside its cell, so layer neighbours never overlap.
CELL_SLACK_RADII = 1.0
#: A row may take this many times as many layers as it needs particles per cell before the
#: strip moves on anyway (where particles keep rolling off a target steeper than the pile stands).
ROW_PATIENCE = 2.0
#: Steps a new particle takes to come to rest on the surface after its fall (the inelastic
#: impact itself and the contacts around it settling).
LANDING_STEPS = 5


def add_walls(world: World, length: float, width: float, friction: float) -> dict[str, int]:
    """The ground and the four walls of a bed of ``length`` × ``width`` (m); body ids by name."""
    planes = {
        "ground": ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
        "wall_start": ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)),
        "wall_end": ((length, 0.0, 0.0), (-1.0, 0.0, 0.0)),
        "wall_left": ((0.0, -0.5 * width, 0.0), (0.0, 1.0, 0.0)),
        "wall_right": ((0.0, 0.5 * width, 0.0), (0.0, -1.0, 0.0)),
    }
    return {
        name: world.add_plane(np.array(p), np.array(n), friction) for name, (p, n) in planes.items()
    }


def make_world(bed: Bed, config: dict[str, Any]) -> tuple[World, dict[str, int]]:
    """A simulation world (``World.from_config(config)``) holding ``bed``.

    It has the ground, the start/end and side walls (module docstring) and the bed's spheres with
    their velocities restored; those at rest count as having rested (:meth:`World.count_as_rested
    <dozerlab.ndem.World.count_as_rested>`), so with ``solver.active_zone`` the settled bed
    outside the zone sleeps from the first step. Returns the world and the body ids by name:
    ``ground``, ``wall_start``, ``wall_end``, ``wall_left``, ``wall_right``.
    """
    world = World.from_config(config)
    ids = add_walls(world, bed.length, bed.width, float(config["material"]["wall_friction"]))
    _add_particles(world, bed.positions, bed.radii, config, bed.velocities, bed.angular_velocities)
    world.count_as_rested()
    return world, ids


def _add_particles(
    world: World,
    positions: np.ndarray,
    radii: np.ndarray,
    config: dict[str, Any],
    velocities: np.ndarray | None = None,
    angular_velocities: np.ndarray | None = None,
) -> np.ndarray:
    m = config["material"]
    return world.add_spheres(
        positions,
        radii,
        m["density"],
        m["friction"],
        m["rolling_resistance"],
        velocities=velocities,
        angular_velocities=angular_velocities,
    )


def _kinetic_energy(world: World) -> float:
    """Mean translational + rotational kinetic energy per particle (J) of the world's spheres."""
    m, r = world.masses, world.radii
    if len(m) == 0:
        return 0.0
    v, w = world.velocities, world.angular_velocities
    e = 0.5 * m * np.einsum("ij,ij->i", v, v) + 0.2 * m * r * r * np.einsum("ij,ij->i", w, w)
    return float(e.mean())


class _Emitter:
    """The strip: where it is, when it lays a layer, where the particles go, when it moves on.

    The ground is divided into rows along x of ``cell_x`` and columns along y of ``cell_y``, both
    wider than the largest particle. Each cell should end up holding ``packing_fraction`` × its
    target volume (target height at its centre × area) in particles. The strip covers ``rows`` rows from row
    ``rear``; a layer puts one particle of random radius at a random spot in each of its cells
    that holds fewer than that (cells wider than a particle keep layer neighbours apart). The
    count is of the particles there now, so what rolls ahead of the strip is not laid twice.
    The strip moves on one row once its rear row holds its share, or after ``ROW_PATIENCE`` times
    the layers that would take, where the target is steeper than the pile can stand.
    """

    def __init__(self, scenario: str, config: dict[str, Any], rng: np.random.Generator):
        check_terrain(scenario, config, height_bound())
        b = config["bed"]
        self.length, self.width = float(b["length"]), float(b["width"])
        self.r, self.spread, self.gap = (
            float(b["radius"]),
            float(b["radius_dispersion"]),
            float(b["emitter_gap"]),
        )
        self.rng = rng
        cell = 2.0 * self.r * (1.0 + self.spread) + CELL_SLACK_RADII * self.r
        if cell > min(self.length, self.width):
            raise ValueError(
                f"bed.length ({self.length} m) and bed.width ({self.width} m) must both exceed "
                f"one emitter cell of {cell:.3g} m (bed.radius {self.r} m is too large)"
            )
        self.n_rows, self.columns = int(self.length // cell), int(self.width // cell)
        self.cell_x, self.cell_y = self.length / self.n_rows, self.width / self.columns
        self.rows = min(STRIP_ROWS, self.n_rows)
        height = target_height(
            scenario,
            config,
            (np.arange(self.n_rows)[:, None] + 0.5) * self.cell_x,
            (np.arange(self.columns)[None, :] + 0.5) * self.cell_y - 0.5 * self.width,
        )
        mean_volume = 4.0 / 3.0 * np.pi * self.r**3 * (1.0 + self.spread**2)
        #: Particles each cell should hold (n_rows, columns).
        self.quota = float(b["packing_fraction"]) * self.cell_x * self.cell_y * height / mean_volume
        self.estimate = round(self.quota.sum())
        if self.estimate < 1:
            raise ValueError("the scenario's bed heights are too low to hold a single particle")
        self.rear, self.tries = 0, 0
        # A layer must land before the next is laid over it, or each new layer would sit on the
        # falling one before it and the drops would grow without bound; the strip also keeps
        # below emitter_speed.
        self.drop_speed, g = (
            float(b["emitter_drop_speed"]),
            float(np.linalg.norm(config["solver"]["gravity"])),
        )
        fall = 2.0 * self.gap / (self.drop_speed + np.sqrt(self.drop_speed**2 + 4.0 * g * self.gap))
        self.period = max(
            fall + LANDING_STEPS * float(b["dt"]), self.cell_x / float(b["emitter_speed"])
        )
        self.in_flight = 0.9 * max(self.drop_speed, np.sqrt(2.0 * g * self.gap))

    @property
    def done(self) -> bool:
        """Whether the strip has passed the end of the domain."""
        return self.rear >= self.n_rows

    def layer(
        self, pos: np.ndarray, rad: np.ndarray, vel: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The next layer: positions (k, 3) and radii (k,) of new particles; moves the strip on.

        Each particle sits ``emitter_gap`` (up to twice that, at random) above the height at which
        it would first touch the ground or a landed particle (``pos`` (N, 3), ``rad`` (N,),
        velocities ``vel`` (N, 3) slower than ``in_flight``) dropped straight down, so it lands
        soon, at a low speed. None is created where it would overlap a particle still falling:
        stacking on those would raise every later layer further (a runaway rain).
        """
        rng = self.rng
        last = min(self.rear + self.rows, self.n_rows)
        counts = np.zeros((last - self.rear, self.columns))
        row = np.floor(pos[:, 0] / self.cell_x).astype(np.int64)
        inside = (row >= self.rear) & (row < last)
        col = np.clip(
            np.floor((pos[inside, 1] + 0.5 * self.width) / self.cell_y).astype(np.int64),
            0,
            self.columns - 1,
        )
        np.add.at(counts, (row[inside] - self.rear, col), 1.0)
        if counts[0].sum() >= self.quota[self.rear].sum() or self.tries >= ROW_PATIENCE * (
            self.quota[self.rear].max() + 1.0
        ):
            self.rear, self.tries = self.rear + 1, 0
            return np.zeros((0, 3)), np.zeros(0)
        self.tries += 1
        ix, iy = np.nonzero(counts < self.quota[self.rear : last])
        ix = ix + self.rear
        n = ix.size
        radius = self.r * (1.0 + self.spread * rng.uniform(-1.0, 1.0, n))
        cx = (ix + 0.5) * self.cell_x + (0.5 * self.cell_x - radius) * rng.uniform(-1.0, 1.0, n)
        cy = (
            -0.5 * self.width
            + (iy + 0.5) * self.cell_y
            + (0.5 * self.cell_y - radius) * rng.uniform(-1.0, 1.0, n)
        )
        lift = self.gap * (1.0 + rng.uniform(0.0, 1.0, n))
        reach = 2.0 * self.r * (1.0 + self.spread)
        near = (pos[:, 0] > self.rear * self.cell_x - reach) & (
            pos[:, 0] < last * self.cell_x + reach
        )
        p, r = pos[near], rad[near]
        flying = np.linalg.norm(vel[near], axis=1) > self.in_flight
        reach2 = (
            (r[None, :] + radius[:, None]) ** 2
            - (p[None, :, 0] - cx[:, None]) ** 2
            - (p[None, :, 1] - cy[:, None]) ** 2
        )
        rest = np.where(
            (reach2 > 0.0) & ~flying[None, :], p[None, :, 2] + np.sqrt(np.maximum(reach2, 0.0)), 0.0
        )
        cz = np.maximum(radius, rest.max(axis=1, initial=0.0)) + lift
        clash = ((reach2 > (cz[:, None] - p[None, :, 2]) ** 2) & flying[None, :]).any(axis=1)
        return np.column_stack([cx, cy, cz])[~clash], radius[~clash]


def build_bed(scenario: str, config: dict[str, Any], *, progress: bool = True) -> Bed:
    """Build and settle the bed of ``scenario`` (a preset or a scenario the config's ``scenarios``
    defines, :mod:`dozerlab.terrain`) from a validated config.

    Uses ``bed.dt`` and ``bed.iterations`` for the solver, the rest of the ``solver`` section
    (``solver.active_zone``'s rest speed, rest time and wake load for the zone, whether it is on
    being ``bed.active_zone``), ``material`` and ``seed``. The strip makes one pass, with
    ``bed.active_zone`` the grains at rest asleep; then the bed settles, every grain stepped (at least
    ``bed.awake_settle_time`` with the zone), until the mean kinetic energy per particle is
    below ``bed.settle_kinetic_energy``.
    Raises ConfigError if the terrain cannot be built (:func:`dozerlab.terrain.check_terrain`),
    DozerlabError if it has not settled ``bed.max_settle_time`` simulated seconds after the
    last layer, or a particle left the domain.
    """
    from tqdm import tqdm

    b, mat = config["bed"], config["material"]
    emitter = _Emitter(scenario, config, np.random.default_rng(int(config["seed"])))
    dt, log_every = float(b["dt"]), int(b["log_every"])
    # every solver and material setting of the config, with the bed's own step, sweeps and zone;
    # the pour's settling was measured with its bed.iterations sweeps every step, and nothing
    # would switch solver.rest_tolerance off in it (no body moves), so that stays out; its
    # sleepers are the settled layers under the strip, measured rigid ("Beds poured with the
    # active zone" in BENCHMARKS.md), not a bed a blade pushes
    world = World.from_config(config)
    world.params = world.params.with_(
        dt=dt,
        iterations=int(b["iterations"]),
        active_zone=bool(b["active_zone"]),
        rest_tolerance=0.0,
        sleeper_compliance=1.0,
    )
    add_walls(world, emitter.length, emitter.width, float(mat["wall_friction"]))
    # The strip needs at least one layer per row; twice the layers the estimate needs, at most.
    emission_steps = int(
        np.ceil((emitter.n_rows + 2.0 * emitter.estimate / emitter.columns) * emitter.period / dt)
    )
    max_steps = emission_steps + int(np.ceil(float(b["max_settle_time"]) / dt))
    threshold = float(b["settle_kinetic_energy"])
    # the grains slept under the layers laid on them compact once woken, a millimetre at speeds
    # the kinetic energy does not see: the bed is stepped whole for a while first
    awake_steps = int(np.ceil(float(b["awake_settle_time"]) / dt)) if b["active_zone"] else 0
    woke = 0
    log_t: list[float] = []
    log_e: list[float] = []
    log_c: list[int] = []
    layers, energy, emission_time = 0, np.inf, np.nan
    start = time.perf_counter()
    bar = tqdm(total=max_steps, desc=f"bed {scenario}", unit="step", disable=not progress)
    step = 0
    try:
        while step < max_steps:
            # Every layer due by the end of this step, each placed above the ones before it.
            while not emitter.done and layers * emitter.period < (step + 1) * dt:
                new_p, new_r = emitter.layer(world.positions, world.radii, world.velocities)
                down = np.zeros((len(new_r), 3))
                down[:, 2] = -emitter.drop_speed
                _add_particles(world, new_p, new_r, config, velocities=down)
                layers += 1
                if emitter.done:
                    emission_time = (step + 1) * dt
                    # the bed settles with every grain stepped: the runs start from it so
                    world.active_zone = False
                    woke = step
            stats = world.step(1)
            step += 1
            if emitter.done or step % log_every == 0:
                # what the log and the settle test read, not every step of the pour
                energy = _kinetic_energy(world)
            if step % log_every == 0:
                log_t.append(step * dt)
                log_e.append(energy)
                log_c.append(int(stats.contacts))
                bar.set_postfix(particles=world.n_spheres, ke=f"{energy:.2e}", refresh=False)
            if step % LOG_LINE_STEPS == 0:
                # the rule's log: file shows progress even where the bar is off (--no-progress)
                log.info(
                    "bed %s step %d (t=%.2f s): %d particles (%d awake), %d layers%s, kinetic "
                    "energy %.3g J per particle (settled below %g), %.1f ms/step",
                    scenario,
                    step,
                    step * dt,
                    world.n_spheres,
                    stats.active,
                    layers,
                    " (all)" if emitter.done else "",
                    energy,
                    threshold,
                    1e3 * (time.perf_counter() - start) / step,
                )
            bar.update(1)
            if emitter.done and energy < threshold and step - woke > awake_steps:
                break
            if not emitter.done and step >= emission_steps:
                raise DozerlabError(
                    f"bed {scenario}: the emitter strip reached only x = {emitter.rear * emitter.cell_x:.3g} m "
                    f"of {emitter.length} m in {step * dt:.3g} s; the bed does not reach its target height "
                    f"(check bed.packing_fraction and the scenarios heights)"
                )
    finally:
        bar.close()
    if step % log_every:
        log_t.append(step * dt)
        log_e.append(energy)
        log_c.append(world.contact_count)
    if energy >= threshold:
        raise DozerlabError(
            f"bed {scenario} did not settle within bed.max_settle_time = {b['max_settle_time']} s after "
            f"the last layer (kinetic energy per particle {energy:.3g} J > bed.settle_kinetic_energy "
            f"{threshold:g} J); raise bed.max_settle_time or bed.iterations"
        )
    bed = Bed(
        scenario=scenario,
        length=emitter.length,
        width=emitter.width,
        positions=world.positions.copy(),
        radii=world.radii.copy(),
        masses=world.masses.copy(),
        velocities=world.velocities.copy(),
        angular_velocities=world.angular_velocities.copy(),
        material=dict(mat),
        seed=int(config["seed"]),
        settle_time=np.array(log_t),
        settle_kinetic_energy=np.array(log_e),
        settle_contacts=np.array(log_c),
        info={
            "time": step * dt,
            "steps": step,
            "emission_time": emission_time,
            "wall_time": time.perf_counter() - start,
            "dt": dt,
            "iterations": int(b["iterations"]),
            "layers": layers,
            "bed": dict(b),
            "shape": dict(config["scenarios"][scenario]),
            # what a heightmap held when the bed was built: its path may later hold another
            **(
                {"heightmap_sha256": sha256_file(hm)}
                if (hm := heightmap_file(scenario, config))
                else {}
            ),
        },
    )
    _check_inside(bed)
    return bed


def _check_inside(bed: Bed) -> None:
    """Raise DozerlabError if a particle centre lies outside the walled domain (a blown-up build)."""
    p, slack = bed.positions, 0.5 * bed.radii
    outside = (
        (p[:, 0] < -slack)
        | (p[:, 0] > bed.length + slack)
        | (np.abs(p[:, 1]) > 0.5 * bed.width + slack)
        | (p[:, 2] < -slack)
    )
    if outside.any():
        raise DozerlabError(
            f"bed {bed.scenario}: {int(outside.sum())} particles left the domain while settling"
        )
