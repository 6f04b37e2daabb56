"""The adaptive sweep's jobs: a round's points, a round's record, the learning curve."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab import tracking
from dozerlab.adaptive import design, plots
from dozerlab.adaptive.curve import COLUMNS as CURVE_COLUMNS
from dozerlab.adaptive.curve import (
    LOOP_COLUMNS,
    Design,
    HeldOutLoop,
    cumulative,
    curve_rows,
    held_out_loop,
    loop_figures,
    mean_by_size,
    random_designs,
    write_curve,
)
from dozerlab.integrity import read_json
from dozerlab.runtime import (
    DozerlabError,
    OutputKind,
    atomic_output,
    first_line_is,
    job_outputs,
    json_with,
    marked_folder,
)
from dozerlab.sweep import (
    SweepPoint,
    by_role,
    field_path,
    parse_point,
    reduced_path,
    sweep_points,
    twin_path,
)

#: A round's points.csv.
POINTS_CSV = OutputKind(
    "a dozerlab round's points CSV", first_line_is(",".join(design.COLUMNS)), "adaptive-points"
)
#: A round's record: its points and the models' held-out errors after it.
RECORD_JSON = OutputKind(
    "a dozerlab adaptive round record",
    json_with(("round", "runs", "points", "errors")),
    "adaptive-record",
)
#: The learning curve's CSV.
CURVE_CSV = OutputKind(
    "a dozerlab learning curve CSV", first_line_is(",".join(CURVE_COLUMNS)), "adaptive-curve"
)
#: The learning curve's figures (the curve, the rounds on the sweep map).
CURVE_PLOTS = marked_folder("a dozerlab folder of learning-curve figures", "adaptive-plots")


def read_run(path: str | Path) -> tuple[SweepPoint, np.ndarray, np.ndarray]:
    """An NDEM run's point (from its path), summaries and their run-to-run spread (N)."""
    from dozerlab.fields.store import open_store

    force = np.asarray(open_store(path)["force"].values, dtype=float)
    p = parse_point(path)
    return (
        SweepPoint(p.scenario, p.speed, p.depth),
        design.run_summaries(force),
        design.run_noise(force),
    )


def read_rounds(paths: Sequence[str | Path]) -> list[list[design.Scored]]:
    """The rows of rounds 0, 1, … from their ``points.csv`` files, in the order given."""
    return [design.read_points(p) for p in paths]


def points_job(
    config: Mapping[str, Any],
    round_index: int,
    previous: Sequence[str | Path],
    stores: Sequence[str | Path],
    out: str | Path,
) -> list[design.Scored]:
    """Write round ``round_index``'s ``points.csv`` at ``out``: the initial design for round 0,
    else the picks of the ensemble fitted to the NDEM runs ``stores`` of the earlier rounds,
    whose ``points.csv`` are ``previous`` (rounds 0 … round_index - 1, in order)."""
    out = Path(out)
    with job_outputs(("--out", out, POINTS_CSV)):
        if len(previous) != round_index:
            raise DozerlabError(
                f"round {round_index} needs the points of the {round_index} rounds before it, got {len(previous)}"
            )
        if round_index == 0:
            rows = design.round_zero(config)
        else:
            taken = [r.point for rows_ in read_rounds(previous) for r in rows_]
            runs = {p: (y, n) for p, y, n in map(read_run, stores)}
            missing = [f"{p.scenario}/{p.name}" for p in taken if p not in runs]
            if missing:
                raise DozerlabError(
                    f"round {round_index}: no NDEM run given for {', '.join(missing)} of the earlier rounds"
                )
            rows = design.next_round(config, round_index, taken, runs)
        with atomic_output(out, POINTS_CSV) as tmp:
            design.write_points(tmp, rows)
    return rows


def record_job(
    config: Mapping[str, Any],
    rounds: Sequence[str | Path],
    validations: Sequence[str | Path],
    out: str | Path,
    *,
    models: Sequence[str | Path] = (),
    results: str | Path | None = None,
) -> dict[str, Any]:
    """Record the last of ``rounds`` (``points.csv`` of rounds 0 … r): JSON at ``out`` with its
    points, the NDEM training runs so far and the held-out errors of the models trained on them
    (``validations``: their validation JSONs), and one MLflow run ``adaptive/round~r``.

    With ``models`` (the round's model directories) and ``results``, and the learning curve's
    reduced figures on (:func:`loop_curve`), ``reduced`` holds each model's reduced-simulation
    figures (:func:`~dozerlab.adaptive.curve.loop_figures`) on the held-out replay loops."""
    out = Path(out)
    with job_outputs(("--out", out, RECORD_JSON)):
        all_rows = read_rounds(rounds)
        r = len(all_rows) - 1
        errors = {}
        for v in validations:
            doc = read_json(v, "a validation JSON")
            errors[str(doc["model"])] = float(doc["overall"]["force_x"]["rel_rmse"])
        reduced: dict[str, dict[str, float]] = {}
        if models and results is not None and loop_curve(config):
            from dozerlab.learn.pyfunc import FORMAT

            loops = held_out_loops(config, results)
            for m in models:
                module, meta = FORMAT.load(m)
                reduced[str(meta.get("kind") or Path(m).name)] = loop_figures(module, loops)
        picked = all_rows[r]
        points = [
            {"scenario": s.point.scenario, "speed": s.point.speed, "depth": s.point.depth}
            | {"score": s.score, "why": s.why}
            for s in picked
        ]
        runs = sum(len(x) for x in all_rows)
        record = {"round": r, "runs": runs, "points": points, "errors": errors}
        if reduced:
            record["reduced"] = reduced
        params = {
            "round": r,
            "points": ";".join(f"{s.point.scenario}/{s.point.name}" for s in picked),
        }
        with tracking.job_run(
            config,
            tracking.run_name("adaptive", f"round~{r}"),
            rule="adaptive_record",
            tags={"round": r},
            params=params,
        ) as run:
            with atomic_output(out, RECORD_JSON) as tmp:
                tmp.write_text(json.dumps(record, indent=1))
            if run is not None:
                scores = [s.score for s in picked if np.isfinite(s.score)]
                metrics = {"runs": float(runs), "points": float(len(points))}
                metrics |= {f"heldout_force_rel_rmse_{m}": e for m, e in errors.items()}
                metrics |= {
                    f"{k}_{m}": v
                    for m, fig in reduced.items()
                    for k, v in fig.items()
                    if np.isfinite(v)
                }
                if scores:
                    metrics |= {"score_max": max(scores), "score_min": min(scores)}
                run.log_metrics(metrics)
                run.log_artifact(Path(rounds[-1]))
                run.log_artifact(out)
    return record


def curve_job(
    config: Mapping[str, Any],
    rounds: Sequence[str | Path],
    results: str | Path,
    out: str | Path,
    plots_dir: str | Path,
) -> list[dict[str, Any]]:
    """The learning curve: ``learning_curve.csv`` at ``out`` and its figures in ``plots_dir``.

    The adaptive design's rounds (their ``points.csv``, in order) and, with
    ``sweep.adaptive.compare``, the grid and ``random_designs`` random designs of the same sizes
    drawn from the candidates; every run's store and the held-out points' are read from
    ``results`` (the workflow's paths). One MLflow run ``adaptive/learning-curve``.
    """
    out, pdir = Path(out), Path(plots_dir)
    with job_outputs(("--out", out, CURVE_CSV), ("--plots", pdir, CURVE_PLOTS)):
        rows_by_round = read_rounds(rounds)
        designs = comparison_designs(config, [[s.point for s in r] for r in rows_by_round])
        rows = learning_curve(config, designs, results)
        with tracking.job_run(
            config,
            tracking.run_name("adaptive", "learning-curve"),
            rule="adaptive_curve",
            params={"rounds": len(rounds)},
        ) as run:
            with atomic_output(out, CURVE_CSV) as tmp:
                write_curve(tmp, rows)
            with atomic_output(pdir, CURVE_PLOTS) as tmp:
                tmp.mkdir()
                plots.learning_curve(rows, tmp / "learning_curve.png")
                plots.rounds_map(config, rows_by_round, tmp / "rounds_map.png")
            if run is not None:
                for name in ("adaptive", "grid", "random"):
                    for column in ("heldout_force_rel_rmse", *LOOP_COLUMNS):
                        for n, e in mean_by_size(rows, name, column).items():
                            if np.isfinite(e):
                                run.log_metrics({f"{name}_{column}": e}, step=n)
                run.log_artifact(out)
                run.log_artifacts(pdir, artifact_path="plots")
    return rows


def comparison_designs(
    config: Mapping[str, Any], rounds: Sequence[Sequence[SweepPoint]]
) -> list[Design]:
    """The adaptive design and, with ``sweep.adaptive.compare``, the grid and the random designs
    (seeds: the config's ``seed`` + 0, 1, …) of the adaptive design's sizes."""
    ad = config["sweep"]["adaptive"]
    sets = cumulative(rounds)
    designs = [Design("adaptive", -1, sets)]
    if ad["compare"]:
        grid = tuple(by_role(sweep_points(config), "train"))
        designs.append(
            Design("grid", -1, (tuple(SweepPoint(p.scenario, p.speed, p.depth) for p in grid),))
        )
        pool = design.candidate_pool(config)
        seeds = [int(config["seed"]) + i for i in range(ad["random_designs"])]
        designs += random_designs(pool, [len(s) for s in sets], seeds)
    return designs


def design_points(
    config: Mapping[str, Any], rounds: Sequence[Sequence[SweepPoint]]
) -> list[SweepPoint]:
    """Every training run the learning curve needs, each once."""
    return list(
        dict.fromkeys(p for d in comparison_designs(config, rounds) for s in d.sets for p in s)
    )


def learning_curve(
    config: Mapping[str, Any], designs: Sequence[Design], results: str | Path
) -> list[dict[str, Any]]:
    """The curve's rows for ``designs``, stores read from ``results`` (see :func:`curve_job`)."""
    from dozerlab.learn.data import load_store

    points = list(dict.fromkeys(p for d in designs for s in d.sets for p in s))
    stores = {p: load_store(field_path(results, p)) for p in points}
    every = sweep_points(config)
    held = {
        g: [load_store(field_path(results, p)) for p in by_role(every, g)]
        for g in ("interpolation", "extrapolation")
    }
    model = config["sweep"]["adaptive"]["curve_model"]
    if not loop_curve(config):
        return curve_rows(designs, stores, held, config, model)
    loops = held_out_loops(config, results)
    return curve_rows(designs, stores, held, config, model, loops, config["reduced"]["force_model"])


def loop_curve(config: Mapping[str, Any]) -> bool:
    """Whether the learning curve measures the reduced simulation too: with
    ``sweep.adaptive.compare`` (the grid's runs and its force model, which the replay runs of
    the held-out points ask for, are made anyway) and ``replay`` among
    ``reduced.dynamics_models``."""
    return (
        bool(config["sweep"]["adaptive"]["compare"])
        and "replay" in (config["reduced"]["dynamics_models"])
    )


def loop_points(config: Mapping[str, Any]) -> list[SweepPoint]:
    """The held-out points whose replay loops the curve reads: the curve's own groups."""
    every = sweep_points(config)
    return [p for g in ("interpolation", "extrapolation") for p in by_role(every, g)]


def loop_inputs(config: Mapping[str, Any], results: str | Path) -> list[Path]:
    """What the curve's reduced figures read (none when off, :func:`loop_curve`): the replay
    runs' stores of :func:`loop_points` and, with ``reduced.twin.enabled``, their twins'."""
    if not loop_curve(config):
        return []
    twins = bool(config["reduced"]["twin"]["enabled"])
    out = [reduced_path(results, "replay", p) for p in loop_points(config)]
    return out + ([twin_path(results, p) for p in loop_points(config)] if twins else [])


def held_out_loops(config: Mapping[str, Any], results: str | Path) -> list[HeldOutLoop]:
    """The replay loops of :func:`loop_points`, with their NDEM runs and twins, from ``results``."""
    twins = bool(config["reduced"]["twin"]["enabled"])
    return [
        held_out_loop(
            reduced_path(results, "replay", p),
            field_path(results, p),
            twin_path(results, p) if twins else None,
        )
        for p in loop_points(config)
    ]
