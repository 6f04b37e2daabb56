"""The learning curve: held-out force error against the number of NDEM training runs.

Each *design* is a sequence of nested training sets: the adaptive design's rounds (round 0,
then rounds 0-1, …), the grid (all its runs), and random designs of the adaptive design's sizes
drawn from its candidates (one permutation per seed, its first n runs: a random design grows as
the adaptive one does). For each training set the curve's force model is trained and measured
on the same held-out points; a row per (design, seed, runs).

Beside it, the reduced simulation's pushing-force error on the held-out points: with ``replay``
(NDEM's own fields drive the loop) the loop's grains and fields do not depend on the training
set, only the force its force model reads off them does. So each training set's force model of
the loop's kind (``reduced.force_model``; replay's is fitted to NDEM's fields) is applied to the
fields of every held-out point's replay loop (its reduced store), row by row as the loop applies
it, and the pushing force is measured against NDEM's as ``compare-reduced`` measures it
(:func:`dozerlab.reduce.compare.force_lp_rel_rmse`), beside the point's twin.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dozerlab.learn.data import StoreData
from dozerlab.runtime import DozerlabError
from dozerlab.sweep import SweepPoint

if TYPE_CHECKING:  # torch: not for the workflow's input functions, which import this module
    from dozerlab.learn.models import ForceModel

#: The reduced simulation's figures (:func:`loop_figures`), means over the held-out points.
LOOP_COLUMNS = (
    "reduced_force_lp_rel_rmse",
    "twin_force_lp_rel_rmse",
    "reduced_force_lp_rel_rmse_skill",
)
#: The columns of ``learning_curve.csv``; errors are relative RMSEs of the pushing force
#: (force_x) on the held-out points, all together and per group, as fractions; then the loop's
#: force model kind and the reduced simulation's figures (:data:`LOOP_COLUMNS`, fractions).
COLUMNS = (
    "design",
    "seed",
    "runs",
    "model",
    "heldout_force_rel_rmse",
    "interpolation_force_rel_rmse",
    "extrapolation_force_rel_rmse",
    "reduced_force_model",
    *LOOP_COLUMNS,
)
#: The columns that hold names, not numbers.
TEXT_COLUMNS = ("design", "model", "reduced_force_model")


@dataclass(frozen=True)
class Design:
    """A design's name, its seed (-1 when not random) and its nested training sets."""

    name: str
    seed: int
    sets: tuple[tuple[SweepPoint, ...], ...]


@dataclass(frozen=True)
class HeldOutLoop:
    """A held-out point's replay loop: its reduced store (``loop``: the loop's fields; the force
    rows before ``warmup`` are the warm-up's: NDEM's, or none on a blade clear of the bed), NDEM's force rows (T, 3) N aligned with it, the
    rows' period (s), and the twin's ``force_lp_rel_rmse`` over the same rows (NaN without one)."""

    loop: StoreData
    ndem_force: np.ndarray
    row_dt: float
    warmup: int
    twin_error: float


def held_out_loop(
    reduced: str | Path, ndem: str | Path, twin: str | Path | None = None
) -> HeldOutLoop:
    """Read a held-out point's replay loop (its reduced store ``reduced``), NDEM's run of the
    point (``ndem``) and, if given, its twin (``twin``): every store read and checked whole."""
    from dozerlab.fields.store import open_store
    from dozerlab.learn.data import load_store
    from dozerlab.reduce.compare import force_lp_rel_rmse

    loop = load_store(reduced)
    nd = open_store(ndem)
    force = nd["force"].values.astype(np.float64)
    time = nd["time"].values
    row_dt = float(np.median(np.diff(time))) if len(time) > 1 else 1.0
    for what, path, rows in (("reduced", reduced, loop.density.shape[0]),) + (
        (("twin", twin, open_store(twin).sizes["time"]),) if twin is not None else ()
    ):
        if rows != force.shape[0]:
            raise DozerlabError(
                f"the {what} store {path} has {rows} rows but NDEM's {ndem} {force.shape[0]}"
            )
    warmup = int(open_store(reduced).attrs.get("warmup_rows", 0))
    twin_error = float("nan")
    if twin is not None:
        twin_force = open_store(twin)["force"].values.astype(np.float64)
        twin_error = force_lp_rel_rmse(twin_force, force, row_dt, slice(warmup, None))
    return HeldOutLoop(loop, force, row_dt, warmup, twin_error)


def loop_force_error(model: ForceModel, run: HeldOutLoop) -> float:
    """``force_lp_rel_rmse`` of the reduced run ``run`` had its loop read its force off its
    fields with ``model``: the warm-up rows keep the stored force, as the loop's do."""
    from dozerlab.learn.pyfunc import predict_arrays
    from dozerlab.reduce.compare import force_lp_rel_rmse

    s = run.loop
    pred = predict_arrays(
        model,
        {"velocity": s.velocity, "density": s.density, "blade_velocity": s.blade_velocity},
    )
    force = s.target[:, :3].astype(np.float64)
    force[run.warmup :] = pred[run.warmup :, :3]
    return force_lp_rel_rmse(force, run.ndem_force, run.row_dt, slice(run.warmup, None))


def loop_figures(model: ForceModel, runs: Sequence[HeldOutLoop]) -> dict[str, float]:
    """The reduced simulation's figures of ``model`` over the held-out loops ``runs``, each the
    mean over the points as ``compare-reduced``'s overall: ``reduced_force_lp_rel_rmse``,
    ``twin_force_lp_rel_rmse`` and ``reduced_force_lp_rel_rmse_skill`` (the point's error over
    its twin's; NaN where no point has one)."""
    from dozerlab.reduce.compare import skills

    errors, twins, skill = [], [], []
    for run in runs:
        e = loop_force_error(model, run)
        errors.append(e)
        twins.append(run.twin_error)
        k = skills({"force_lp_rel_rmse": e}, {"force_lp_rel_rmse": run.twin_error})
        skill.append(k["force_lp_rel_rmse_skill"])

    def mean(values: Sequence[float | None]) -> float:
        ok = [v for v in values if v is not None and np.isfinite(v)]
        return float(np.mean(ok)) if ok else float("nan")

    return {
        "reduced_force_lp_rel_rmse": mean(errors),
        "twin_force_lp_rel_rmse": mean(twins),
        "reduced_force_lp_rel_rmse_skill": mean(skill),
    }


def cumulative(rounds: Sequence[Sequence[SweepPoint]]) -> tuple[tuple[SweepPoint, ...], ...]:
    """The adaptive design's training sets: rounds 0..r for each r."""
    out: list[tuple[SweepPoint, ...]] = []
    acc: list[SweepPoint] = []
    for r in rounds:
        acc += list(r)
        out.append(tuple(acc))
    return tuple(out)


def random_designs(
    pool: Sequence[SweepPoint], sizes: Sequence[int], seeds: Sequence[int]
) -> list[Design]:
    """Random designs of ``sizes`` drawn from ``pool``: per seed one permutation of the pool,
    whose first n points are the design of size n (sizes above the pool's are left out)."""
    designs = []
    for seed in seeds:
        order = np.random.default_rng(seed).permutation(len(pool))
        sets = tuple(tuple(pool[i] for i in order[:n]) for n in sizes if n <= len(pool))
        designs.append(Design("random", int(seed), sets))
    return designs


def rel_rmse(result: Mapping[str, Any]) -> float:
    """The pushing force's relative RMSE of an :func:`~dozerlab.learn.validate.evaluate` result."""
    return float(result["overall"]["force_x"]["rel_rmse"])


def curve_rows(
    designs: Sequence[Design],
    stores: Mapping[SweepPoint, StoreData],
    held_out: Mapping[str, Sequence[StoreData]],
    config: Mapping[str, Any],
    model: str,
    loops: Sequence[HeldOutLoop] = (),
    loop_model: str = "",
) -> list[dict[str, Any]]:
    """Train ``model`` on each design's training sets (stores by point, roles ignored) and measure
    it on the held-out stores of each group; one row of :data:`COLUMNS` per set. A training set
    met twice (the grid's and a random design's full pool, say) is trained once.

    With ``loops`` (the held-out points' replay loops), ``loop_model`` (the loop's force model
    kind; ``model``'s own fit is reused when they agree) trained on the same set gives the
    reduced simulation's figures (:func:`loop_figures`); without, they are NaN."""
    from dozerlab.learn.train import train_model
    from dozerlab.learn.validate import evaluate

    done: dict[frozenset[tuple[str, str]], dict[str, float]] = {}
    every = [s for group in held_out.values() for s in group]
    nan = float("nan")
    rows = []
    for d in designs:
        for pts in d.sets:
            key = frozenset(p.key for p in pts)
            if key not in done:
                train = [stores[_plain(p)] for p in pts]
                trained = train_model(model, train, dict(config))
                errors = {"heldout": rel_rmse(evaluate(trained.model, every))}
                for g, group in held_out.items():
                    errors[g] = rel_rmse(evaluate(trained.model, list(group))) if group else nan
                if loops:
                    fit = (
                        trained
                        if loop_model == model
                        else train_model(loop_model, train, dict(config))
                    )
                    errors |= loop_figures(fit.model, loops)
                done[key] = errors
            e = done[key]
            rows.append(
                {
                    "design": d.name,
                    "seed": d.seed,
                    "runs": len(pts),
                    "model": model,
                    "heldout_force_rel_rmse": e["heldout"],
                    "interpolation_force_rel_rmse": e.get("interpolation", float("nan")),
                    "extrapolation_force_rel_rmse": e.get("extrapolation", nan),
                    "reduced_force_model": loop_model if loops else "",
                }
                | {k: e.get(k, nan) for k in LOOP_COLUMNS}
            )
    return rows


def _plain(p: SweepPoint) -> SweepPoint:
    return SweepPoint(p.scenario, p.speed, p.depth)


def write_curve(path: Path, rows: Sequence[Mapping[str, Any]]) -> None:
    """``learning_curve.csv``: :data:`COLUMNS`, errors with 6 significant digits."""
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: f"{v:.6g}" if isinstance(v, float) else v for k, v in r.items()})


def read_curve(path: str | Path) -> list[dict[str, Any]]:
    """The rows of ``learning_curve.csv``, numbers parsed; a curve written before the reduced
    simulation's columns reads with them empty (``""``, NaN)."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    empty = {"reduced_force_model": ""} | dict.fromkeys(LOOP_COLUMNS, float("nan"))
    return [
        empty
        | {
            k: (v if k in TEXT_COLUMNS else int(v) if k in ("seed", "runs") else float(v))
            for k, v in r.items()
        }
        for r in rows
    ]


def mean_by_size(
    rows: Sequence[Mapping[str, Any]], design: str, column: str = "heldout_force_rel_rmse"
) -> dict[int, float]:
    """A design's mean of ``column`` (a held-out error) per number of runs (over its seeds)."""
    out: dict[int, list[float]] = {}
    for r in rows:
        if r["design"] == design:
            out.setdefault(int(r["runs"]), []).append(float(r[column]))
    return {n: float(np.mean(v)) for n, v in sorted(out.items())}
