"""The reduced run of a sweep point measured against its NDEM run.

Per point (both runs start from the same settled bed and follow the same trajectory):

- **height accuracy** after the pass: 1 − Σ|h_red − h_ndem| / Σ|h_ndem − h_bed| over the bed's
  height field (``trajectory.subdivisions`` cells, the field the trajectory planner uses): 1 is
  NDEM's bed exactly, 0 is no better than leaving the bed as it was;
- **force**: relative RMSE of the pushing force (x) and of |F| over the rows the reduced loop
  made (the NDEM warm-up rows excluded), RMSE / RMS of NDEM's;
- **fields**: relative L2 of the velocity (mass-weighted with NDEM's density, world frame,
  sqrt(Σ ρ|v − v_ndem|²) / sqrt(Σ ρ|v_ndem|²), so empty bins count for nothing) and of the
  density, over all the reduced rows together (a per-row mean would be dominated by the rows
  before the blade meets the bed, where NDEM's velocity is near zero), and as curves per row;
- **final positions** of the grains that moved (more than ``reduced.moved_radii`` radii from the
  start in either run): the sliced Earth mover's distance between the two clouds — the mean,
  over 64 fixed directions, of the exact 1-D EMD of the projections (equal-size clouds: the mean
  |difference| of the sorted projections). It is a lower bound of the 3-D EMD and needs no
  optimal-transport library; the per-grain mean distance (the same grain in both runs) is
  reported beside it as an upper bound;
- **validity**: the largest overlap over the radius during the loop and in the final state, the
  deepest penetration of ground, walls or blade in the final state (both runs; above 0.1 mm it
  counts as "through"), grains outside the bed's box;
- **speed-up**: NDEM's stepping-loop wall time over the reduced loop's (``wall_time_s``: same
  trajectory, so the same simulated time) and, when the Snakemake benchmark records exist, the
  whole jobs' wall times.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.reduce.projection import Bodies, candidate_pairs
from dozerlab.runtime import DozerlabError

#: Directions of the sliced EMD (fixed: the figure is reproducible).
SLICES = 64
#: Penetration of ground, walls or blade (m) that counts as "through" at the least: grains the
#: reduced loop never touched keep the µm overlaps of NDEM's compliant contacts with the ground.
#: Where NDEM's own final state of the point lies deeper (its compliant contacts: 0.5–0.7 mm on
#: the default sweep), that depth is the limit.
THROUGH_TOLERANCE = 1e-4


def height_accuracy(h_red: np.ndarray, h_ndem: np.ndarray, h_bed: np.ndarray) -> float:
    """1 − Σ|h_red − h_ndem| / Σ|h_ndem − h_bed| of height fields of one shape (m).

    NaN when NDEM left the bed unchanged (nothing to reproduce).
    """
    moved = float(np.abs(h_ndem - h_bed).sum())
    if moved == 0.0:
        return float("nan")
    return 1.0 - float(np.abs(h_red - h_ndem).sum()) / moved


def gaussian_smooth(a: np.ndarray, sigma_cells: float) -> np.ndarray:
    """``a`` (Nx, Ny) smoothed by a Gaussian of ``sigma_cells`` cells along both axes, the
    edges extended by their values (a wall does not pull the surface down)."""
    if sigma_cells <= 0:
        return np.asarray(a, dtype=np.float64).copy()
    half = max(1, int(np.ceil(3.0 * sigma_cells)))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma_cells) ** 2)
    k /= k.sum()
    out = np.asarray(a, dtype=np.float64)
    for axis in (0, 1):
        pad = [(0, 0), (0, 0)]
        pad[axis] = (half, half)
        padded = np.pad(out, pad, mode="edge")
        out = np.apply_along_axis(lambda v: np.convolve(v, k, mode="valid"), axis, padded)
    return out


def smoothed_surface(
    positions: np.ndarray, radii: np.ndarray, length: float, width: float, sigma: float
) -> np.ndarray:
    """The spheres' top surface (m) on a lattice of σ/4 cells over the bed, smoothed by a
    Gaussian of ``sigma`` (m): the terrain at the scale ``sigma``, shape (Nx, Ny).

    Positions (N, 3) and radii (N,) in m. Two NDEM runs of one point from beds a micrometre
    apart agree on it far better than cell by cell at the grain scale, where the chaos of the
    grains' contacts decides which grain ends up where.
    """
    from dozerlab.scenarios.heightfield import height_field

    cell = sigma / 4.0
    shape = (max(1, round(length / cell)), max(1, round(width / cell)))
    _, h = height_field(positions, radii, length, width, shape)
    return gaussian_smooth(h, sigma / (length / shape[0]))


def low_pass(series: np.ndarray, dt: float, window: float) -> np.ndarray:
    """The moving mean of ``series`` (T, …) sampled every ``dt`` s over ``window`` s (centred,
    the ends averaged over what the window holds)."""
    n = max(1, round(window / dt))
    a = np.asarray(series, dtype=np.float64)
    c = np.concatenate([np.zeros((1,) + a.shape[1:]), np.cumsum(a, axis=0)])
    i = np.arange(a.shape[0])
    lo, hi = np.maximum(i - n // 2, 0), np.minimum(i - n // 2 + n, a.shape[0])
    shape = (-1,) + (1,) * (a.ndim - 1)
    return (c[hi] - c[lo]) / (hi - lo).reshape(shape)


def relative_rmse(pred: np.ndarray, true: np.ndarray) -> float:
    """RMSE / RMS of ``true`` over all elements (NaN when ``true`` is all zero)."""
    rms = float(np.sqrt(np.mean(np.square(true, dtype=np.float64))))
    err = float(np.sqrt(np.mean(np.square(pred - true, dtype=np.float64))))
    return err / rms if rms > 0 else float("nan")


def field_errors(
    v: np.ndarray, rho: np.ndarray, v_true: np.ndarray, rho_true: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-row L2 error of velocity (mass-weighted by ``rho_true``) and density, (T,) each,
    relative to the truth's root-mean-square row norm over the run.

    v, v_true (T, Nx, Ny, Nz, 3) m/s; rho, rho_true (T, Nx, Ny, Nz) kg/m³. NaN where the truth
    is zero all run. (Over each row's own norm, the rows before the blade reaches the material,
    whose truth barely moves, read as errors of 400 on the default sweep and flattened the rest.)
    """
    axes = tuple(range(1, rho_true.ndim))
    w = rho_true.astype(np.float64)
    num_v = (w * np.square(v - v_true, dtype=np.float64).sum(-1)).sum(axes)
    den_v = (w * np.square(v_true, dtype=np.float64).sum(-1)).sum(axes)
    num_r = np.square(rho - rho_true, dtype=np.float64).sum(axes)
    den_r = np.square(rho_true, dtype=np.float64).sum(axes)
    dv, dr = float(den_v.mean()), float(den_r.mean())
    return (
        np.sqrt(num_v / dv) if dv > 0 else np.full(num_v.shape, np.nan),
        np.sqrt(num_r / dr) if dr > 0 else np.full(num_r.shape, np.nan),
    )


def _global_l2(v: np.ndarray, v_true: np.ndarray, rho_true: np.ndarray) -> float:
    """Mass-weighted relative L2 of velocity over all rows and bins together."""
    w = rho_true.astype(np.float64)
    den = float((w * np.square(v_true, dtype=np.float64).sum(-1)).sum())
    num = float((w * np.square(v - v_true, dtype=np.float64).sum(-1)).sum())
    return float(np.sqrt(num / den)) if den > 0 else float("nan")


def relative_l2(a: np.ndarray, truth: np.ndarray) -> float:
    """‖a − truth‖ / ‖truth‖ over all elements (NaN when the truth is zero)."""
    den = float(np.sqrt(np.square(truth, dtype=np.float64).sum()))
    return (
        float(np.sqrt(np.square(a - truth, dtype=np.float64).sum())) / den
        if den > 0
        else float("nan")
    )


def sliced_emd(a: np.ndarray, b: np.ndarray, slices: int = SLICES, seed: int = 0) -> float:
    """Sliced Earth mover's distance (m) between two equal-size point clouds (N, 3)."""
    if a.shape != b.shape:
        raise ValueError(f"clouds must have the same shape, got {a.shape} and {b.shape}")
    if len(a) == 0:
        return 0.0
    d = np.random.default_rng(seed).normal(size=(slices, a.shape[1]))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pa, pb = np.sort(a @ d.T, axis=0), np.sort(b @ d.T, axis=0)
    return float(np.abs(pa - pb).mean())


def outside_box(positions: np.ndarray, length: float, width: float, tol: float = 1e-6) -> int:
    """Grains whose centre is outside the bed's box x ∈ [0, L], |y| ≤ W/2, z ≥ 0."""
    x, y, z = positions.T
    bad = (x < -tol) | (x > length + tol) | (np.abs(y) > width / 2 + tol) | (z < -tol)
    return int(bad.sum())


def largest_overlap(positions: np.ndarray, radii: np.ndarray) -> float:
    """Largest sphere–sphere overlap over the smaller radius (0 if none)."""
    pi, pj = candidate_pairs(positions, radii, 0.0)
    if pi.size == 0:
        return 0.0
    gap = radii[pi] + radii[pj] - np.linalg.norm(positions[pi] - positions[pj], axis=1)
    return float(max(0.0, (gap / np.minimum(radii[pi], radii[pj])).max()))


def body_penetration(positions: np.ndarray, radii: np.ndarray, bodies: Bodies) -> float:
    """Deepest penetration (m) of any sphere into any plane or box (0 if none)."""
    from dozerlab.ndem.contacts import body_contacts

    _, _, _, gap = body_contacts(
        np.ascontiguousarray(positions),
        np.ascontiguousarray(radii),
        np.zeros(len(radii)),
        bodies.kind,
        bodies.centre,
        bodies.rotation,
        bodies.half,
        bodies.normal,
    )
    return float(max(0.0, gap.max())) if gap.size else 0.0


def _bodies_at(bed: Any, config: Mapping[str, Any], tip: np.ndarray) -> Bodies:
    """Ground, walls and the blade with its tip at ``tip`` (3,) m, as in the runs."""
    from dozerlab.ndem import World
    from dozerlab.reduce.simulation import bodies_of
    from dozerlab.scenarios.blade import add_blade
    from dozerlab.scenarios.build import add_walls

    world = World.from_config(dict(config))
    add_walls(world, bed.length, bed.width, float(config["material"]["wall_friction"]))
    return bodies_of(world, add_blade(world, np.asarray(tip, dtype=np.float64), dict(config)))


def job_seconds(benchmark: str | Path | None) -> float | None:
    """Wall time (s) in a Snakemake benchmark record, or None when there is none."""
    if benchmark is None or not Path(benchmark).is_file():
        return None
    with open(benchmark) as fh:
        rows = list(csv.DictReader(fh, delimiter="\t"))
    return float(rows[0]["s"]) if rows else None


def compare_point(
    ndem_store: str | Path,
    reduced_store: str | Path,
    bed_path: str | Path,
    ndem_state: str | Path,
    reduced_state: str | Path,
    config: Mapping[str, Any],
    *,
    ndem_benchmark: str | Path | None = None,
    reduced_benchmark: str | Path | None = None,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The metrics of one point (module doc) and the series its plots draw.

    Returns (metrics, series): series holds ``time`` (T,), ``force_ndem``/``force_reduced``
    (T, 3) N, ``velocity_error``/``density_error`` (T,), ``height_x`` (Nx,) and the y-mean
    height profiles ``height_bed``/``height_ndem``/``height_reduced`` (Nx,) m, ``warmup`` rows.
    """
    from dozerlab.fields.store import open_store
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.heightfield import height_field

    nd, rd = open_store(ndem_store), open_store(reduced_store)
    if nd.sizes != rd.sizes:
        raise DozerlabError(
            f"{reduced_store} ({dict(rd.sizes)}) is not aligned with {ndem_store} ({dict(nd.sizes)})"
        )
    warm = int(rd.attrs.get("warmup_rows", 0))
    bed, end_n, end_r = Bed.load(bed_path), Bed.load(ndem_state), Bed.load(reduced_state)
    if not (bed.count == end_n.count == end_r.count):
        raise DozerlabError("the bed and the two final states hold different grain counts")
    sub = config["trajectory"]["subdivisions"]
    hx, h0 = height_field(bed.positions, bed.radii, bed.length, bed.width, sub)
    _, hn = height_field(end_n.positions, bed.radii, bed.length, bed.width, sub)
    _, hr = height_field(end_r.positions, bed.radii, bed.length, bed.width, sub)
    fn, fr = nd["force"].values.astype(np.float64), rd["force"].values.astype(np.float64)
    ev, er = field_errors(
        rd["velocity"].values, rd["density"].values, nd["velocity"].values, nd["density"].values
    )
    moved_r = float(config["reduced"]["moved_radii"]) * bed.radii
    moved = (np.linalg.norm(end_n.positions - bed.positions, axis=1) > moved_r) | (
        np.linalg.norm(end_r.positions - bed.positions, axis=1) > moved_r
    )
    a, b = end_n.positions[moved], end_r.positions[moved]
    final_bodies = _bodies_at(bed, config, rd["blade_position"].values[-1])
    wall_n, wall_r = nd.attrs.get("wall_time_s"), rd.attrs.get("wall_time_s")
    job_n, job_r = job_seconds(ndem_benchmark), job_seconds(reduced_benchmark)
    tail = slice(warm, None)
    metrics: dict[str, Any] = {
        "scenario": rd.attrs["scenario"],
        "speed": rd.attrs["speed"],
        "depth": rd.attrs["depth"],
        "dynamics_model": rd.attrs.get("dynamics_model"),
        "force_model": rd.attrs.get("force_model"),
        "rows": int(rd.sizes["time"]),
        "warmup_rows": warm,
        "height_accuracy": height_accuracy(hr, hn, h0),
        "force_x_rel_rmse": relative_rmse(fr[tail, 0], fn[tail, 0]),
        "force_rel_rmse": relative_rmse(
            np.linalg.norm(fr[tail], axis=1), np.linalg.norm(fn[tail], axis=1)
        ),
        "velocity_rel_l2": float(
            _global_l2(
                rd["velocity"].values[tail], nd["velocity"].values[tail], nd["density"].values[tail]
            )
        ),
        "density_rel_l2": relative_l2(rd["density"].values[tail], nd["density"].values[tail]),
        "moved_grains": int(moved.sum()),
        "final_emd_m": sliced_emd(a, b),
        "final_mean_distance_m": float(np.linalg.norm(a - b, axis=1).mean()) if len(a) else 0.0,
        "max_overlap_loop": float(rd.attrs.get("max_overlap", np.nan)),
        "max_overlap_final": largest_overlap(end_r.positions, bed.radii),
        "max_overlap_final_ndem": largest_overlap(end_n.positions, bed.radii),
        "body_depth_final_m": body_penetration(end_r.positions, bed.radii, final_bodies),
        "body_depth_final_ndem_m": body_penetration(end_n.positions, bed.radii, final_bodies),
        "left_bed": outside_box(end_r.positions, bed.length, bed.width),
        "left_bed_ndem": outside_box(end_n.positions, bed.length, bed.width),
        "loop_wall_s": wall_r,
        "ndem_loop_wall_s": wall_n,
        "loop_speedup": wall_n / wall_r if wall_n and wall_r else None,
        "job_wall_s": job_r,
        "ndem_job_wall_s": job_n,
        "job_speedup": job_n / job_r if job_n and job_r else None,
        "phase_ms": json.loads(rd.attrs.get("phase_ms", "{}")),
    }
    series = {
        "time": nd["time"].values,
        "force_ndem": fn,
        "force_reduced": fr,
        "velocity_error": ev,
        "density_error": er,
        "height_x": hx,
        "height_bed": h0.mean(axis=1),
        "height_ndem": hn.mean(axis=1),
        "height_reduced": hr.mean(axis=1),
        "warmup": np.array(warm),
    }
    return metrics, series


def targets_met(metrics: Mapping[str, Any], targets: Mapping[str, float]) -> dict[str, bool | None]:
    """Which of ``reduced.targets`` one point meets (None where the figure is missing)."""

    def check(value: Any, ok: Any) -> bool | None:
        if value is None or (isinstance(value, float) and not np.isfinite(value)):
            return None
        return bool(ok(value))

    return {
        "height_accuracy": check(
            metrics["height_accuracy"], lambda v: v >= targets["height_accuracy"]
        ),
        "force_rmse": check(metrics["force_x_rel_rmse"], lambda v: v <= targets["force_rmse"]),
        "loop_speedup": check(metrics["loop_speedup"], lambda v: v >= targets["loop_speedup"]),
        "job_speedup": check(metrics["job_speedup"], lambda v: v >= targets["job_speedup"]),
        # after projection: the final state's figure also holds grains the loop never touched,
        # with NDEM's own compliant overlaps (``max_overlap_final_ndem``)
        "max_overlap": check(metrics["max_overlap_loop"], lambda v: v <= targets["max_overlap"]),
        "nothing_left": metrics["left_bed"] == 0,
        "nothing_through": metrics["body_depth_final_m"]
        <= max(THROUGH_TOLERANCE, metrics.get("body_depth_final_ndem_m") or 0.0),
    }
