"""The reduced run of a sweep point measured against its NDEM run.

Per point (both runs start from the same settled bed and follow the same trajectory):

- **height accuracy** after the pass: 1 − Σ|h_red − h_ndem| / Σ|h_ndem − h_bed| over the bed's
  height field (``trajectory.subdivisions`` cells, the field the trajectory planner uses): 1 is
  NDEM's bed exactly, 0 is no better than leaving the bed as it was;
- **smoothed surface accuracy**: the same ratio on the spheres' top surface over a lattice of
  σ/4 cells smoothed by a Gaussian of σ = one mean grain diameter: the scale on which two NDEM
  runs from beds a micrometre apart agree (the grain scale is their chaos);
- **where the surface departs**: that accuracy's error split over the swath the blade cut, the
  strips beside it (the windrows) and the bed ahead of the blade's last position (the carried
  pile), each part's Σ|h − h_ndem| and Σ(h − h_ndem) over the whole bed's Σ|h_ndem − h_bed|
  (:func:`surface_errors`);
- **force**: relative RMSE of the pushing force (x) and of |F| over the rows the reduced loop
  made (the warm-up rows excluded), RMSE / RMS of NDEM's; the pushing force low-passed
  over 0.1 s (a centred moving mean, :data:`FORCE_WINDOW`), its relative RMSE, and the relative
  error of its mean over those rows;
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
  whole jobs' wall times: NDEM's job of the point against the point's share of the reduced job
  that ran it with the model's other points (:func:`job_shares`);
- **twin and skill**: with the point's twin (NDEM from the bed with every grain moved by a
  micrometre, ``reduced.twin``) the twin is measured against NDEM the same way, over the same
  rows (``twin_<figure>``), and each figure's skill is the run's over the twin's
  (``<figure>_skill``: accuracy / twin's accuracy, error / twin's error; :data:`FIGURES`);
- **NDEM's expected run**: with more twin draws (``reduced.twin.draws``) the twin's figures are
  their means, and the run and NDEM's own run are both measured against the draws' mean
  low-passed pushing force and mean smoothed surface, the estimate of the run NDEM's chaos
  scatters about (``expected_<figure>``, ``ndem_expected_<figure>`` and their ratio
  ``expected_<figure>_skill``; :data:`EXPECTED_FIGURES`): a model that predicts the expected
  run scores below 1, where against one draw even a perfect one scores about 1/√2 of a twin.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
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


def surface_regions(
    shape: tuple[int, int], length: float, width: float, path: np.ndarray, blade_width: float
) -> dict[str, np.ndarray]:
    """Boolean masks (Sx, Sy) of the parts of the bed (``length`` × ``width`` m, a lattice of
    ``shape`` cells like :func:`smoothed_surface`'s) its error is split over
    (:data:`SURFACE_REGIONS`): ``ahead`` of the blade's last position (x at or beyond its tip's),
    and behind it the ``swath`` the blade cut (within half ``blade_width`` (m) of the path's y at
    that x) and the strips ``beside`` it, where the windrows lie. ``path`` (T, 3): the blade
    tip's positions (m) row by row; cells before the path's start take its first y."""
    nx, ny = shape
    x = (np.arange(nx) + 0.5) * length / nx
    y = (np.arange(ny) + 0.5) * width / ny - width / 2
    px, py = path[:, 0], path[:, 1]
    order = np.argsort(px, kind="stable")
    inside = np.abs(y[None, :] - np.interp(x, px[order], py[order])[:, None]) < blade_width / 2
    behind = np.broadcast_to((x < px[-1])[:, None], shape)
    return {"swath": behind & inside, "beside": behind & ~inside, "ahead": ~behind}


def surface_errors(
    surface: np.ndarray, ndem: np.ndarray, bed: np.ndarray, regions: Mapping[str, np.ndarray]
) -> dict[str, float]:
    """Where a smoothed surface departs from NDEM's (all (Sx, Sy), m), per region of
    :func:`surface_regions`: ``surface_error_<region>`` = Σ|h − h_ndem| over the region, and
    ``surface_excess_<region>`` = Σ(h − h_ndem) over it (above 0: too much material there), both
    over Σ|h_ndem − h_bed| over the whole bed, the smoothed-surface accuracy's denominator: the
    errors of the regions add up to 1 − the accuracy. NaN when NDEM left the bed unchanged."""
    moved = float(np.abs(ndem - bed).sum())
    diff = surface - ndem
    out = {}
    for name, mask in regions.items():
        err, excess = (
            (float(np.abs(diff[mask]).sum()) / moved, float(diff[mask].sum()) / moved)
            if moved > 0.0
            else (float("nan"), float("nan"))
        )
        out[f"surface_error_{name}"] = err
        out[f"surface_excess_{name}"] = excess
    return out


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


def force_lp_rel_rmse(force: np.ndarray, ndem: np.ndarray, row_dt: float, rows: slice) -> float:
    """``force_lp_rel_rmse``: the relative RMSE over ``rows`` of the pushing force (column 0 of
    the (T, 3) N rows ``force``) against NDEM's (``ndem``), both low-passed over
    :data:`FORCE_WINDOW` (rows ``row_dt`` s apart) first."""
    lp, lp_ndem = (low_pass(f[:, 0], row_dt, FORCE_WINDOW) for f in (force, ndem))
    return relative_rmse(lp[rows], lp_ndem[rows])


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


def job_shares(job_s: float | None, loop_s: list[float | None]) -> list[float | None]:
    """Each point's share (s) of one job that ran several reduced loops: its own loop's wall
    time ``loop_s[i]`` plus an equal part of the rest of the job ``job_s`` (start-up, imports,
    models, kernels, each run's reading and writing). All None without the job's record or a
    loop's time; a job shorter than its loops' sum is a record of another job: refused."""
    if job_s is None or not loop_s or any(t is None for t in loop_s):
        return [None] * len(loop_s)
    loops = [float(t) for t in loop_s if t is not None]
    rest = job_s - sum(loops)
    if rest < 0:
        raise DozerlabError(
            f"the reduce job's benchmark record ({job_s:.2f} s) is shorter than its "
            f"{len(loops)} loops ({sum(loops):.2f} s): it is not the record of these runs"
        )
    return [t + rest / len(loops) for t in loops]


#: The figures measured against NDEM, for a reduced run and for the twin alike: an accuracy
#: (1 is NDEM's result exactly, higher is better) or an error (0 is NDEM's, lower is better).
#: Each has a skill: the run's figure over the twin's (NDEM's own reproducibility).
FIGURES = {
    "height_accuracy": "accuracy",
    "surface_accuracy": "accuracy",
    "force_x_rel_rmse": "error",
    "force_lp_rel_rmse": "error",
    "force_mean_rel_err": "error",
    "velocity_rel_l2": "error",
    "density_rel_l2": "error",
    "final_emd_m": "error",
}
#: The figures measured against NDEM's expected run (the mean over the twin draws), both kinds as
#: in :data:`FIGURES`.
EXPECTED_FIGURES = {"surface_accuracy": "accuracy", "force_lp_rel_rmse": "error"}
#: The parts of the bed the smoothed surface's error is split over (:func:`surface_regions`).
SURFACE_REGIONS = ("swath", "beside", "ahead")
#: The window (s) of the low-passed pushing force: the scale NDEM's force reproduces.
FORCE_WINDOW = 0.1


@dataclass(frozen=True)
class Reference:
    """NDEM's run of a point, read once for every run measured against it: the bed and NDEM's
    final state, their grain-scale height fields and smoothed surfaces (m), the force rows
    (T, 3) N, the fields (velocity (T, Nx, Ny, Nz, 3) m/s, density (T, Nx, Ny, Nz) kg/m³), the
    rows' times and period (s), the stepping loop's wall time (s), the store's sizes, the blade
    tip's path (T, 3) m and the smoothed surface's regions (:func:`surface_regions`)."""

    bed: Any
    end: Any
    height_x: np.ndarray
    height_bed: np.ndarray
    height_ndem: np.ndarray
    surface_bed: np.ndarray
    surface_ndem: np.ndarray
    force: np.ndarray
    velocity: np.ndarray
    density: np.ndarray
    time: np.ndarray
    row_dt: float
    wall_time_s: float | None
    sizes: dict[str, int]
    subdivisions: tuple[int, int]
    moved_radii: float
    path: np.ndarray
    regions: dict[str, np.ndarray]

    @property
    def sigma(self) -> float:
        """The smoothed surface's Gaussian σ (m): one mean grain diameter."""
        return surface_sigma(self.bed.radii)


def surface_sigma(radii: np.ndarray) -> float:
    """σ (m) of the smoothed surface: one mean grain diameter of ``radii`` (m)."""
    return 2.0 * float(np.mean(radii))


def reference(
    ndem_store: str | Path, bed_path: str | Path, ndem_state: str | Path, config: Mapping[str, Any]
) -> Reference:
    """NDEM's run of a point (its store and final state) and the bed it started from."""
    from dozerlab.fields.store import open_store
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.heightfield import height_field

    nd = open_store(ndem_store)
    bed, end = Bed.load(bed_path), Bed.load(ndem_state)
    if bed.count != end.count:
        raise DozerlabError(
            f"different grain counts: {ndem_state} holds {end.count}, {bed_path} {bed.count}"
        )
    nx, ny = (int(n) for n in config["trajectory"]["subdivisions"])
    sub = (nx, ny)
    hx, h0 = height_field(bed.positions, bed.radii, bed.length, bed.width, sub)
    _, hn = height_field(end.positions, bed.radii, bed.length, bed.width, sub)
    sigma = surface_sigma(bed.radii)
    surface_bed = smoothed_surface(bed.positions, bed.radii, bed.length, bed.width, sigma)
    path = nd["blade_position"].values.astype(np.float64)
    time = nd["time"].values
    return Reference(
        bed=bed,
        end=end,
        height_x=hx,
        height_bed=h0,
        height_ndem=hn,
        surface_bed=surface_bed,
        surface_ndem=smoothed_surface(end.positions, bed.radii, bed.length, bed.width, sigma),
        force=nd["force"].values.astype(np.float64),
        velocity=nd["velocity"].values,
        density=nd["density"].values,
        time=time,
        row_dt=float(np.median(np.diff(time))) if len(time) > 1 else 1.0,
        wall_time_s=nd.attrs.get("wall_time_s"),
        sizes={str(k): int(v) for k, v in nd.sizes.items()},
        subdivisions=sub,
        moved_radii=float(config["reduced"]["moved_radii"]),
        path=path,
        regions=surface_regions(
            surface_bed.shape, bed.length, bed.width, path, float(config["blade"]["width"])
        ),
    )


def against_ndem(
    ref: Reference, store: Any, end: Any, rows: slice
) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """The :data:`FIGURES` of one run (its store, an xarray Dataset aligned row by row with
    NDEM's, and its final state, a ``Bed``) against NDEM's (``ref``), the force and field
    figures over ``rows``, with the surface's error by region (:func:`surface_errors`); and its
    series: ``force`` (T, 3) N, ``velocity_error`` /
    ``density_error`` (T,), ``height`` (Nx, Ny) m, ``moved`` (the grains either run moved)."""
    from dozerlab.scenarios.heightfield import height_field

    bed = ref.bed
    if end.count != bed.count:
        raise DozerlabError(
            f"different grain counts: a final state holds {end.count}, the bed {bed.count}"
        )
    _, h = height_field(end.positions, bed.radii, bed.length, bed.width, ref.subdivisions)
    surface = smoothed_surface(end.positions, bed.radii, bed.length, bed.width, ref.sigma)
    force = store["force"].values.astype(np.float64)
    velocity, density = store["velocity"].values, store["density"].values
    ev, er = field_errors(velocity, density, ref.velocity, ref.density)
    mean_ndem = float(ref.force[rows, 0].mean())
    moved_r = ref.moved_radii * bed.radii
    moved = (np.linalg.norm(ref.end.positions - bed.positions, axis=1) > moved_r) | (
        np.linalg.norm(end.positions - bed.positions, axis=1) > moved_r
    )
    a, b = ref.end.positions[moved], end.positions[moved]
    figures = {
        "height_accuracy": height_accuracy(h, ref.height_ndem, ref.height_bed),
        "surface_accuracy": height_accuracy(surface, ref.surface_ndem, ref.surface_bed),
        "force_x_rel_rmse": relative_rmse(force[rows, 0], ref.force[rows, 0]),
        "force_rel_rmse": relative_rmse(
            np.linalg.norm(force[rows], axis=1), np.linalg.norm(ref.force[rows], axis=1)
        ),
        "force_lp_rel_rmse": force_lp_rel_rmse(force, ref.force, ref.row_dt, rows),
        "force_mean_rel_err": (
            abs(float(force[rows, 0].mean()) - mean_ndem) / abs(mean_ndem)
            if mean_ndem != 0
            else float("nan")
        ),
        "velocity_rel_l2": _global_l2(velocity[rows], ref.velocity[rows], ref.density[rows]),
        "density_rel_l2": relative_l2(density[rows], ref.density[rows]),
        "moved_grains": int(moved.sum()),
        "final_emd_m": sliced_emd(a, b),
        "final_mean_distance_m": float(np.linalg.norm(a - b, axis=1).mean()) if len(a) else 0.0,
        **surface_errors(surface, ref.surface_ndem, ref.surface_bed, ref.regions),
    }
    series = {
        "force": force,
        "velocity_error": ev,
        "density_error": er,
        "height": h,
        "surface": surface,
        "moved": moved,
    }
    return figures, series


def against_expected(
    ref: Reference,
    force: np.ndarray,
    surface: np.ndarray,
    draws: Sequence[Mapping[str, np.ndarray]],
    rows: slice,
) -> dict[str, float]:
    """The :data:`EXPECTED_FIGURES` of one run against NDEM's expected run, estimated by the
    mean of ``draws`` (each run's :func:`against_ndem` series: ``force`` (T, 3) N, ``surface``
    (Sx, Sy) m): the low-passed pushing force over ``rows`` against the draws' mean force (the
    mean of their low-passed forces) and the smoothed surface ``surface`` against their mean
    surface, from the bed's (``ref``)."""
    if not draws:
        raise ValueError("NDEM's expected run needs at least one draw")
    mean_force = np.mean([d["force"] for d in draws], axis=0)
    mean_surface = np.mean([d["surface"] for d in draws], axis=0)
    return {
        "surface_accuracy": height_accuracy(surface, mean_surface, ref.surface_bed),
        "force_lp_rel_rmse": force_lp_rel_rmse(force, mean_force, ref.row_dt, rows),
    }


def skills(
    run: Mapping[str, Any], twin: Mapping[str, Any], figures: Mapping[str, str] = FIGURES
) -> dict[str, float | None]:
    """``<figure>_skill``: each of ``figures`` of a run over the twin's (model accuracy / twin
    accuracy, model error / twin error); None where either is missing, not finite, or the
    twin's is 0."""
    out: dict[str, float | None] = {}
    for key in figures:
        a, b = run.get(key), twin.get(key)
        if a is None or b is None or not (np.isfinite(a) and np.isfinite(b)) or b == 0:
            out[f"{key}_skill"] = None
        else:
            out[f"{key}_skill"] = float(a) / float(b)
    return out


def compare_point(
    ndem_store: str | Path,
    reduced_store: str | Path,
    bed_path: str | Path,
    ndem_state: str | Path,
    reduced_state: str | Path,
    config: Mapping[str, Any],
    *,
    ndem_benchmark: str | Path | None = None,
    reduced_job_s: float | None = None,
    twin: tuple[str | Path, str | Path] | None = None,
    draws: Sequence[tuple[str | Path, str | Path]] = (),
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The metrics of one point (module doc) and the series its plots draw.

    ``ndem_benchmark``: the Snakemake benchmark record of the point's NDEM job;
    ``reduced_job_s``: the reduced run's share of its job, s (:func:`job_shares`).

    ``twin``: the point's twin NDEM run (its store and final state), measured against NDEM over
    the same rows: ``twin_<figure>`` and ``<figure>_skill`` (:func:`skills`) join the metrics.
    ``draws``: the point's further twin draws (each a store and final state; with ``twin``
    only): ``twin_<figure>`` are then the means over every draw, ``twin_draws`` their number,
    and the run and NDEM's own run are measured against their mean (:func:`against_expected`):
    ``expected_<figure>``, ``ndem_expected_<figure>``, ``expected_<figure>_skill``.

    Returns (metrics, series): series holds ``time`` (T,), ``force_ndem``/``force_reduced``
    (and ``force_twin``) (T, 3) N, ``force_window`` (s), ``velocity_error``/``density_error``
    (T,), ``height_x`` (Nx,) and the y-mean height profiles ``height_bed``/``height_ndem``/
    ``height_reduced`` (and ``height_twin``) (Nx,) m, ``warmup`` rows, the smoothed surfaces
    ``surface_bed``/``surface_ndem``/``surface_reduced`` (and ``surface_twin``) (Sx, Sy) m over
    the bed's ``extent`` (length, width) m, and the blade tip's ``path`` (T, 3) m and
    ``blade_width`` m (the regions' bounds).
    """
    from dozerlab.fields.store import open_store
    from dozerlab.scenarios.bed import Bed

    ref = reference(ndem_store, bed_path, ndem_state, config)
    rd = open_store(reduced_store)
    if ref.sizes != {str(k): int(v) for k, v in rd.sizes.items()}:
        raise DozerlabError(
            f"{reduced_store} ({dict(rd.sizes)}) is not aligned with {ndem_store} ({ref.sizes})"
        )
    warm = int(rd.attrs.get("warmup_rows", 0))
    tail = slice(warm, None)
    bed, end_r = ref.bed, Bed.load(reduced_state)
    figures, run = against_ndem(ref, rd, end_r, tail)
    final_bodies = _bodies_at(bed, config, rd["blade_position"].values[-1])
    wall_n, wall_r = ref.wall_time_s, rd.attrs.get("wall_time_s")
    job_n, job_r = job_seconds(ndem_benchmark), reduced_job_s
    metrics: dict[str, Any] = {
        "scenario": rd.attrs["scenario"],
        "speed": rd.attrs["speed"],
        "depth": rd.attrs["depth"],
        "dynamics_model": rd.attrs.get("dynamics_model"),
        "force_model": rd.attrs.get("force_model"),
        "rows": int(rd.sizes["time"]),
        "warmup_rows": warm,
        **figures,
        "surface_sigma_m": ref.sigma,
        "max_overlap_loop": float(rd.attrs.get("max_overlap", np.nan)),
        "max_overlap_final": largest_overlap(end_r.positions, bed.radii),
        "max_overlap_final_ndem": largest_overlap(ref.end.positions, bed.radii),
        "body_depth_final_m": body_penetration(end_r.positions, bed.radii, final_bodies),
        "body_depth_final_ndem_m": body_penetration(ref.end.positions, bed.radii, final_bodies),
        "left_bed": outside_box(end_r.positions, bed.length, bed.width),
        "left_bed_ndem": outside_box(ref.end.positions, bed.length, bed.width),
        "loop_wall_s": wall_r,
        "ndem_loop_wall_s": wall_n,
        "loop_speedup": wall_n / wall_r if wall_n and wall_r else None,
        "job_wall_s": job_r,
        "ndem_job_wall_s": job_n,
        "job_speedup": job_n / job_r if job_n and job_r else None,
        "phase_ms": json.loads(rd.attrs.get("phase_ms", "{}")),
    }
    series = {
        "time": ref.time,
        "force_ndem": ref.force,
        "force_reduced": run["force"],
        "force_window": np.array(FORCE_WINDOW),
        "velocity_error": run["velocity_error"],
        "density_error": run["density_error"],
        "height_x": ref.height_x,
        "height_bed": ref.height_bed.mean(axis=1),
        "height_ndem": ref.height_ndem.mean(axis=1),
        "height_reduced": run["height"].mean(axis=1),
        "warmup": np.array(warm),
        "surface_bed": ref.surface_bed,
        "surface_ndem": ref.surface_ndem,
        "surface_reduced": run["surface"],
        "extent": np.array([bed.length, bed.width]),
        "path": ref.path,
        "blade_width": np.array(float(config["blade"]["width"])),
    }
    if draws and twin is None:
        raise ValueError("further twin draws need the twin itself")
    if twin is not None:
        measured = []
        for store_path, state_path in (twin, *draws):
            td = open_store(store_path)
            if ref.sizes != {str(k): int(v) for k, v in td.sizes.items()}:
                raise DozerlabError(
                    f"{store_path} ({dict(td.sizes)}) is not aligned with {ndem_store} "
                    f"({ref.sizes})"
                )
            measured.append(against_ndem(ref, td, Bed.load(state_path), tail))
        twin_figures = measured[0][0]
        if len(measured) > 1:
            twin_figures = {k: float(np.mean([m[k] for m, _ in measured])) for k in twin_figures}
        metrics |= {f"twin_{k}": v for k, v in twin_figures.items()}
        metrics |= skills(figures, twin_figures)
        twin_run = measured[0][1]
        series |= {
            "force_twin": twin_run["force"],
            "height_twin": twin_run["height"].mean(axis=1),
            "surface_twin": twin_run["surface"],
        }
        if draws:
            runs = [r for _, r in measured]
            mine = against_expected(ref, run["force"], run["surface"], runs, tail)
            ndem = against_expected(ref, ref.force, ref.surface_ndem, runs, tail)
            metrics["twin_draws"] = len(runs)
            metrics |= {f"expected_{k}": v for k, v in mine.items()}
            metrics |= {f"ndem_expected_{k}": v for k, v in ndem.items()}
            metrics |= {f"expected_{k}": v for k, v in skills(mine, ndem, EXPECTED_FIGURES).items()}
    return metrics, series


def targets_met(
    metrics: Mapping[str, Any], targets: Mapping[str, float], *, replay: bool = False
) -> dict[str, bool | None]:
    """Which of ``reduced.targets`` one point meets (None where the figure is missing, as the
    skills are without a twin). ``replay``: the run is the replay control (NDEM's own fields),
    held to ``replay_surface_skill``; a learned model's run to ``surface_skill`` and
    ``force_skill``."""

    def check(value: Any, ok: Any) -> bool | None:
        if value is None or (isinstance(value, float) and not np.isfinite(value)):
            return None
        return bool(ok(value))

    surface = metrics.get("surface_accuracy_skill")
    if replay:
        skill = {
            "replay_surface_skill": check(surface, lambda v: v >= targets["replay_surface_skill"])
        }
    else:
        skill = {
            "surface_skill": check(surface, lambda v: v >= targets["surface_skill"]),
            "force_skill": check(
                metrics.get("force_lp_rel_rmse_skill"), lambda v: v <= targets["force_skill"]
            ),
        }
    return skill | {
        "loop_speedup": check(metrics["loop_speedup"], lambda v: v >= targets["loop_speedup"]),
        "job_speedup": check(metrics["job_speedup"], lambda v: v >= targets["job_speedup"]),
        # after projection: the final state's figure also holds grains the loop never touched,
        # with NDEM's own compliant overlaps (``max_overlap_final_ndem``)
        "max_overlap": check(metrics["max_overlap_loop"], lambda v: v <= targets["max_overlap"]),
        "nothing_left": metrics["left_bed"] == 0,
        "nothing_through": metrics["body_depth_final_m"]
        <= max(THROUGH_TOLERANCE, metrics.get("body_depth_final_ndem_m") or 0.0),
    }


def transfer_gap(entries: Sequence[Mapping[str, Any]], target: float) -> dict[str, Any] | None:
    """The smoothed-surface skill on unseen terrain (role ``transfer``) against the seen shapes
    (``interpolation`` and ``extrapolation``): each the mean over its points of
    ``surface_accuracy_skill``, ``gap`` = unseen − seen, ``met`` when |gap| ≤ ``target``
    (``reduced.targets.transfer_skill_gap``). None without a point of either side or a skill
    (no twins)."""

    def mean_skill(roles: tuple[str, ...]) -> float | None:
        values = [
            float(v)
            for e in entries
            if e.get("role") in roles
            and (v := e.get("surface_accuracy_skill")) is not None
            and np.isfinite(v)
        ]
        return float(np.mean(values)) if values else None

    seen = mean_skill(("interpolation", "extrapolation"))
    unseen = mean_skill(("transfer",))
    if seen is None or unseen is None:
        return None
    gap = unseen - seen
    return {
        "surface_skill_seen": seen,
        "surface_skill_unseen": unseen,
        "gap": gap,
        "target": float(target),
        "met": bool(abs(gap) <= target),
    }
