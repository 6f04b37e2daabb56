"""``dozerlab reduce``: one sweep point run by the reduced loop, written like an NDEM run.

The outputs mirror ``dozerlab simulate``'s: a field store in the field-store schema (one row per
sampled step, aligned with the NDEM store of the point) whose attributes add the models used
(``dynamics_model``, ``force_model``), ``wall_time_s`` (the stepping loop's wall time, the NDEM
warm-up included), ``warmup_stepped`` (whether NDEM stepped the warm-up rows: not when the blade
reaches no grain before them) and ``reduced`` (the loop's settings, JSON); and the final particle
state as a bed file. Both appear only when the run succeeds.
"""

from __future__ import annotations

import json
import logging
import time as wallclock
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from dozerlab import __version__
from dozerlab.fields.sampling import SamplingGrid
from dozerlab.fields.store import FieldStoreWriter, field_store_kind
from dozerlab.reduce.projection import Bodies, spheres_near
from dozerlab.reduce.simulation import (
    PhaseTimes,
    ReducedSettings,
    ReducedState,
    bodies_of,
    compile_kernels,
    density_correction,
)
from dozerlab.runtime import DozerlabError
from dozerlab.scenarios.bed import bed_file_kind

log = logging.getLogger(__name__)
#: What ``reduce`` and ``reduce-points`` write: the store and the final state of a reduced run,
#: never replacing NDEM's (or a bed).
REDUCED_STORE = field_store_kind("a dozerlab field store written by reduce", "reduce")
REDUCED_STATE = bed_file_kind("a dozerlab final state (.npz) written by reduce", "reduce-state")


def _blade_reaches(bodies: Bodies, x: np.ndarray, radii: np.ndarray, centres: np.ndarray) -> bool:
    """Whether the blade box (the last of ``bodies``) placed at any of ``centres`` (K, 3) m comes
    within the largest radius of a grain of ``x`` (N, 3) m, ``radii`` (N,) m: steps a solver
    step apart, so no grain slips between two of them unseen."""
    blade = Bodies(
        bodies.kind[-1:],
        np.zeros((1, 3)),
        bodies.rotation[-1:],
        bodies.half[-1:],
        bodies.normal[-1:],
    )
    margin = float(radii.max()) if radii.size else 0.0
    for c in centres:
        blade.centre[0] = c
        if spheres_near(x, radii, blade, margin).size:
            return True
    return False


def reduce_run(
    bed_path: str | Path,
    trajectory_path: str | Path,
    config: dict[str, Any],
    field_model: Any,
    force_model: Any,
    out: str | Path,
    state_out: str | Path,
    *,
    scenario: str | None = None,
    speed: float | None = None,
    depth: float | None = None,
) -> dict[str, float]:
    """Run the reduced loop over one trajectory; write the store ``out`` and state ``state_out``.

    ``field_model`` follows :class:`dozerlab.reduce.models.FieldModel`, ``force_model``
    :class:`dozerlab.reduce.models.ForcePredictor`; ``config`` is a validated config (sections
    solver, material, blade, sampling, reduced). Returns the run's metrics: ``wall_time_s``,
    per-phase ms per store row (``ms_<phase>``), the rows the loop made (``reduced_rows``) and
    the steps the grains took over them (``reduced_steps``, ``reduced.step_rows`` rows each),
    the largest overlap after projection over the radius (``max_overlap``), the deepest body
    penetration the projection iterations left before the final push-out
    (``max_body_depth_m``), whether NDEM stepped the warm-up (``warmup_stepped``, 1 or 0), the
    mean count per step of grains moved, of projection sweeps run and of the contact tests they
    made, and the steps whose largest overlap was taken over the whole bed
    (``beyond_ring_steps``: a grain moved past the projected set's ring).
    Raises :class:`DozerlabError` when the loop diverges, leaving no output.
    """
    from dozerlab.fields.run import load_inputs, moved_bed, sample_row
    from dozerlab.reduce.models import RunFrame
    from dozerlab.scenarios.blade import BladeGeometry, add_blade
    from dozerlab.scenarios.build import make_world

    bed, traj, dt = load_inputs(bed_path, trajectory_path, config)
    every = int(config["sampling"]["every"])
    grid = SamplingGrid.from_config(config)
    settings = ReducedSettings.from_config(config).for_model(field_model.name)
    rows = traj.steps // every
    hist, horizon = int(field_model.history), int(field_model.horizon)
    warmup = max(hist, 1)
    if rows <= warmup:
        raise DozerlabError(
            f"the trajectory has {rows} sampled rows, not more than the field model's history {hist}"
        )
    frame = RunFrame(
        str(trajectory_path),
        rows,
        grid.bins,
        grid.bin_size,
        dt * every,
        {
            "scenario": scenario or bed.scenario,
            "speed": speed if speed is not None else round(traj.speed, 6),
            "depth": depth,
        },
        grid.blade_part,
    )
    field_model.check_run(frame)
    force_model.check_run(frame)
    step_of = (np.arange(rows) + 1) * every  # solver steps done at each row
    blade_v = traj.velocity[step_of - 1].astype(np.float32)
    blade_v_ahead = np.vstack([blade_v, np.zeros((horizon, 3), np.float32)])
    geometry = BladeGeometry.from_config(config)
    vel = np.zeros((rows, *grid.bins, 3), np.float32)
    rho = np.zeros((rows, *grid.bins), np.float32)
    # The field model's velocity history: its own prediction of each row, or the grains' flow
    # (ReducedState.flow) sampled back; resampled, the interpolated field is smoothed once more
    # each row and the pile's motion ahead of the blade fades (reduced.predicted_history).
    flow = np.zeros_like(vel)
    predicted = field_model.name in settings.predicted_history
    # The evolution model's density of each row, which the grains are steered towards
    # (reduced.density_models): the warm-up's rows are NDEM's, as sampled.
    steered = settings.steers(field_model.name)
    field_rho = np.zeros_like(rho)
    solid = float(config["material"]["density"])
    x, y, z = grid.centres()
    attrs = {
        "scenario": scenario or bed.scenario,
        "speed": speed if speed is not None else round(traj.speed, 6),
        "depth": depth,
        **grid.attrs(),
        "dt": dt,
        "iterations": int(config["solver"]["iterations"]),
        "sample_every": every,
        "particle_count": bed.count,
        "seed": int(config["seed"]),
        "dozerlab_version": __version__,
        "config": json.dumps(config, sort_keys=True),
        "dynamics_model": field_model.name,
        "force_model": force_model.name,
        "warmup_rows": warmup,
        "reduced": json.dumps(config["reduced"], sort_keys=True),
    }
    compile_kernels(grid)
    times = PhaseTimes()
    worst_overlap = worst_depth = 0.0
    active, sweeps, tests = [], [], []
    start = wallclock.perf_counter()
    with FieldStoreWriter(
        out,
        x=x,
        y=y,
        z=z,
        attrs=attrs,
        kind=REDUCED_STORE,
        chunk_steps=int(config["sampling"]["chunk_steps"]),
        # one chunk a shard: its rows are written at once after the loop and read whole; with
        # eight inner chunks a shard a run's 346 rows took 78-121 ms to write, with one 45-52 ms
        # (BENCHMARKS.md, "The reduced store in whole shards")
        inner_steps=int(config["sampling"]["chunk_steps"]),
        steps=rows,
    ) as writer:
        # NDEM warm-up: the models' history, from the same bed along the same trajectory.
        world, _ = make_world(bed, config)
        blade = add_blade(world, traj.position[0], config)
        # A blade that reaches no grain before the model's first row leaves NDEM a bed at rest
        # to step: the rows are then the bed as it lies (NDEM's warm-up took 0.4-0.5 s of a
        # ridge run's 2.8-4.1 s on the default sweep, whose blades start 10 cm before the bed;
        # BENCHMARKS.md).
        stepped = _blade_reaches(
            bodies_of(world, blade),
            world.positions,
            world.radii,
            traj.position[: warmup * every + 1] + geometry.tip_offset,
        )
        for i in range(warmup * every):
            if stepped:
                world.set_velocity(blade, traj.velocity[i])
                world.step()
            if (i + 1) % every == 0:
                row = sample_row(world, blade, grid, traj, i + 1, geometry.tip_offset)
                k = (i + 1) // every - 1
                vel[k], rho[k] = row[1], row[2]
                field_rho[k] = row[2]
                flow[k] = row[1]
                writer.append(*row)
        domain_hi = np.array([bed.length, bed.width / 2, bed.positions[:, 2].max() + 1.0])
        state = ReducedState(
            world.positions,
            world.velocities,
            world.radii,
            world.masses,
            bodies_of(world, blade),
            geometry.half_extents,
            geometry.tip_offset,
            grid,
            world.gravity,
            settings,
            np.array([0.0, -bed.width / 2, 0.0]),
            domain_hi,
        )
        t0 = times.add("warmup", start)
        pred_v = pred_rho = None
        first = warmup  # the first row of the reduced step that ends at a sampled row
        steps = 0
        for k in tqdm(range(warmup, rows), desc="reduce", unit="row", disable=None):
            j = (k - warmup) % horizon
            if j == 0:
                pred_v, pred_rho = field_model.predict(
                    flow[k - hist : k],
                    rho[k - hist : k],
                    blade_v_ahead[k - hist : k + horizon],
                    k - 1,
                )
                t0 = times.add("field_inference", t0)
            assert pred_v is not None and pred_rho is not None  # predicted at j == 0, k = warmup
            times.rows += 1
            field_rho[k] = pred_rho[j]
            if (k - warmup) % settings.step_rows == 0:
                first = k
            if k < rows - 1 and k - first < settings.step_rows - 1:
                # a row inside a step: until the grains reach its end, the model's history of
                # the row is its own prediction
                flow[k], vel[k], rho[k] = pred_v[j], pred_v[j], pred_rho[j]
                continue
            # one step over the rows first..k: the grains move by the mean of their fields
            # (the blade moves 1-1.5 cm a row, a third of a bin: the fields' frames all but agree)
            span = k - first + 1
            mean_v = (flow[first:k].sum(axis=0) + pred_v[j]) / span
            tip = traj.position[step_of[k]]
            h = span * every * dt
            # the grains as they start the step (sampled at the last step's end) against the
            # model's density of that row
            steer = (
                density_correction(
                    rho[first - 1],
                    field_rho[first - 1],
                    grid.bin_size,
                    h,
                    settings.density_gain,
                    solid,
                )
                if steered
                else None
            )
            st = state.step(mean_v, pred_rho[j], tip, h, times, steer)
            steps += 1
            worst_overlap = max(worst_overlap, st.max_overlap)
            worst_depth = max(worst_depth, st.body_depth)
            active.append(state.active)
            sweeps.append(st.sweeps)
            tests.append(st.tests)
            t0 = wallclock.perf_counter()
            # every grain: the sums skip those whose box misses the volume, so they read the
            # grains near it in the same order as a gather of them would, without the gather
            if predicted:
                flow[k] = pred_v[j]
                (vel[k],), rho[k] = grid.sample_velocities(
                    state.x, (state.v,), state.r, state.m, tip
                )
            else:  # the fields and the flow in one pass over the grains
                (vel[k], flow[k]), rho[k] = grid.sample_velocities(
                    state.x, (state.v, state.flow), state.r, state.m, tip
                )
            # the rows inside the step: their fields (the store's, and the models' history from
            # here on) between the sampled rows either side, as the grains moved between them
            w = ((np.arange(first, k) - first + 1) / span)[:, None, None, None]
            pairs = [(vel, w[..., None]), (rho, w)] + ([] if predicted else [(flow, w[..., None])])
            for a, wa in pairs:
                a[first:k] = (1.0 - wa) * a[first - 1] + wa * a[k]
            t0 = times.add("sampling", t0)
        # The grains never read the force: every row's in one batched call after the loop.
        force, torque = force_model.predict_rows(vel, rho, blade_v[:rows])
        t0 = times.add("force_inference", t0)
        for k in range(warmup, rows):
            writer.append(
                float(traj.time[step_of[k]]),
                vel[k],
                rho[k],
                force[k],
                torque[k],
                blade_v[k],
                traj.position[step_of[k]],
            )
        times.add("output", t0)
        wall = wallclock.perf_counter() - start
        writer.update_attrs(
            warmup_stepped=stepped,
            wall_time_s=wall,
            max_overlap=worst_overlap,
            phase_ms=json.dumps(times.per_row_ms()),
        )
    moved_bed(
        bed,
        state.x,
        state.v,
        np.zeros_like(state.v),
        {"time": float(traj.time[step_of[-1]]), "dynamics_model": field_model.name},
    ).save(state_out, REDUCED_STATE)
    metrics = {
        "wall_time_s": wall,
        "warmup_s": times.seconds["warmup"],
        "warmup_stepped": float(stepped),
        "max_overlap": worst_overlap,
        "max_body_depth_m": worst_depth,
        "active_grains_mean": float(np.mean(active)) if active else 0.0,
        "projection_sweeps_mean": float(np.mean(sweeps)) if sweeps else 0.0,
        "projection_tests_mean": float(np.mean(tests)) if tests else 0.0,
        "reduced_rows": float(times.rows),
        "reduced_steps": float(steps),
        "beyond_ring_steps": float(state.beyond_ring),
    }
    metrics |= {f"ms_{k}": v for k, v in times.per_row_ms().items()}
    log.info("reduce done: %s", ", ".join(f"{k}={v:.4g}" for k, v in metrics.items()))
    return metrics
