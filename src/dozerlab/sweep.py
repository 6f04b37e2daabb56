"""Sweep points and the workflow's result paths, the one place that spells them.

A sweep point is a scenario, a blade speed (m/s) and a cut depth (m). Its files are named
``speed~{speed}_depth~{depth}`` with each number in its canonical form (:func:`fmt_number`):
the shortest plain decimal that reads back as the same float, always with a decimal point
(``1.0``, ``0.1``, ``0.05``). The Snakefile builds its targets with these functions, so the
paths it asks for are the ones a user types, and :func:`parse_point` reads any of them back.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from string import Formatter
from typing import Any

import numpy as np

from dozerlab.runtime import ConfigError, check_name

ROLES = ("train", "interpolation", "extrapolation", "transfer")
#: The roles of the points held out of training: the models are validated on these.
HELD_OUT_ROLES = ROLES[1:]
#: What a speed or depth looks like in a path.
NUMBER_PATTERN = r"[0-9]+\.[0-9]+"
#: What the Snakefile's wildcards accept as a speed or depth: any spelling, so that
#: :func:`check_canonical` can name the right one (or the reason) instead of a missing rule.
WILDCARD_PATTERN = r"[^_/]+"
#: Units of the numbers in a path, for messages.
UNITS = {"speed": "m/s", "depth": "m"}
_POINT = re.compile(
    rf"speed~(?P<speed>{NUMBER_PATTERN})_depth~(?P<depth>{NUMBER_PATTERN})(\.[A-Za-z]+)?"
)


def fmt_number(value: float) -> str:
    """The canonical spelling of a speed or depth in a path: ``1.0``, ``0.1``, ``0.00001``."""
    value = float(value)
    if not np.isfinite(value) or value < 0:
        raise ValueError(f"a sweep number must be finite and >= 0, got {value}")
    return np.format_float_positional(value, unique=True, trim="0")


def check_canonical(name: str, text: str) -> float:
    """Parse a speed/depth as spelled in a path; refuse non-canonical spellings.

    ``speed~1`` and ``speed~1.00`` would be distinct files holding the same run, so only
    :func:`fmt_number`'s spelling is accepted; the error names the spelling to use.
    """
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{name} '{text}' is not a number (write it like {name}~1.0)") from None
    if not np.isfinite(value) or value <= 0:
        raise ValueError(
            f"{name} '{text}' is not a {name} (allowed: a finite number > 0 {UNITS.get(name, '')})"
        )
    if fmt_number(value) != text:
        raise ValueError(
            f"{name} '{text}' is not in canonical form; ask for {name}~{fmt_number(value)}"
        )
    return value


@dataclass(frozen=True)
class SweepPoint:
    """One simulation of the sweep: scenario, blade speed (m/s), cut depth (m) and its role."""

    scenario: str
    speed: float
    depth: float
    role: str = "train"

    @property
    def name(self) -> str:
        """``speed~{speed}_depth~{depth}``, the file stem of this point's outputs."""
        return point_name(self.speed, self.depth)

    @property
    def key(self) -> tuple[str, str]:
        """(scenario, name): identifies the point's files whatever its role."""
        return self.scenario, self.name


def point_name(speed: float, depth: float) -> str:
    """The file stem of a sweep point, e.g. ``speed~1.0_depth~0.1``."""
    return POINT_STEM.format(speed=fmt_number(speed), depth=fmt_number(depth))


def parse_point(path: str | Path, role: str = "train") -> SweepPoint:
    """The sweep point of a result path ``…/{scenario}/speed~{speed}_depth~{depth}.{ext}``."""
    p = Path(path)
    m = _POINT.fullmatch(p.name)
    if m is None:
        raise ValueError(f"path '{path}' is not named speed~{{speed}}_depth~{{depth}}[.ext]")
    return SweepPoint(p.parent.name, float(m["speed"]), float(m["depth"]), role)


def sweep_points(cfg: Mapping[str, Any]) -> list[SweepPoint]:
    """Every point of the validated config's sweep: the training grid, then the held-out points.

    Raises :class:`~dozerlab.runtime.ConfigError` when a held-out point is also a training point
    (the models would see it in training) or is listed twice, or a transfer point's scenario has
    training points (it would not be unseen terrain).
    """
    sweep = cfg["sweep"]
    points = [
        SweepPoint(s, float(v), float(d), "train")
        for s in sweep["scenarios"]
        for v in sweep["speeds"]
        for d in sweep["depths"]
    ]
    seen = {p.key: "sweep grid" for p in points}
    for role in HELD_OUT_ROLES:
        for i, item in enumerate(sweep[role]):
            point = SweepPoint(item["scenario"], float(item["speed"]), float(item["depth"]), role)
            if role == "transfer" and point.scenario in sweep["scenarios"]:
                raise ConfigError(
                    f"config field 'sweep.transfer[{i}].scenario': {point.scenario} is in "
                    "sweep.scenarios, so the models train on it (allowed: a scenario of no "
                    "training point)"
                )
            if point.key in seen:
                raise ConfigError(
                    f"config field 'sweep.{role}[{i}]': {point.scenario} {point.name} is already in the "
                    f"{seen[point.key]} (allowed: a point outside the training grid, listed once)"
                )
            seen[point.key] = f"sweep.{role}"
            points.append(point)
    return points


def by_role(points: Iterable[SweepPoint], role: str) -> list[SweepPoint]:
    """The points of one role (``train``, ``interpolation``, ``extrapolation`` or ``transfer``)."""
    if role not in ROLES:
        raise ValueError(f"role must be one of {ROLES}, got '{role}'")
    return [p for p in points if p.role == role]


#: The file stem of a sweep point's outputs, with the rules' wildcards.
POINT_STEM = "speed~{speed}_depth~{depth}"
#: Every result path, relative to the results directory, with the rules' wildcards
#: (``{scenario}``, ``{speed}``, ``{depth}``, ``{model}``): the rules' outputs are
#: :func:`pattern`, and the path functions below fill the same templates.
PATHS = {
    "bed": "beds/{scenario}.npz",
    "bed_plot": "beds/{scenario}.png",
    "trajectory": f"trajectories/{{scenario}}/{POINT_STEM}.csv",
    "trajectory_plot": f"trajectories/{{scenario}}/{POINT_STEM}.png",
    "field": f"fields/{{scenario}}/{POINT_STEM}.zarr",
    "field_plots": f"plots/{{scenario}}/{POINT_STEM}",
    "simulate_benchmark": f"benchmarks/simulate/{{scenario}}/{POINT_STEM}.tsv",
    "state": f"states/{{scenario}}/{POINT_STEM}.npz",
    "twin": f"twins/{{scenario}}/{POINT_STEM}.zarr",
    "twin_state": f"twins/{{scenario}}/{POINT_STEM}.npz",
    "twin_benchmark": f"benchmarks/twin/{{scenario}}/{POINT_STEM}.tsv",
    "twin_draw": f"twins/{{scenario}}/{POINT_STEM}_draw~{{draw}}.zarr",
    "twin_draw_state": f"twins/{{scenario}}/{POINT_STEM}_draw~{{draw}}.npz",
    "twin_draw_benchmark": f"benchmarks/twin/{{scenario}}/{POINT_STEM}_draw~{{draw}}.tsv",
    "reduced": f"reduced/{{dynamics_model}}/{{scenario}}/{POINT_STEM}.zarr",
    "reduced_state": f"reduced/{{dynamics_model}}/{{scenario}}/{POINT_STEM}.npz",
    "reduce_benchmark": "benchmarks/reduce/{dynamics_model}/held_out.tsv",
    "reduce_training_benchmark": "benchmarks/reduce/{dynamics_model}/training_points.tsv",
    "reduced_comparison": "reduced/{dynamics_model}.json",
    "reduced_comparison_plots": "reduced/{dynamics_model}/compare",
    "loop_force_model": "reduced/{dynamics_model}/force_model",
    "model": "models/{model}",
    "validation": "validation/{model}.json",
    "validation_plots": "validation/{model}",
    "dynamics_model": "dynamics/{model}",
    "dynamics_validation": "dynamics/{model}.json",
    "dynamics_plots": "dynamics/plots/{model}",
    "report": "report/index.html",
    "report_dir": "report",
    "report_animations": "report/animations",
}
# An adaptive sweep's files (sweep.adaptive, dozerlab.adaptive): per round {round} (0, 1, …) its
# points, the models trained on the runs so far and their validations, its record.
PATHS |= {
    "adaptive_points": "adaptive/round~{round}/points.csv",
    "adaptive_model": "adaptive/round~{round}/models/{model}",
    "adaptive_validation": "adaptive/round~{round}/validation/{model}.json",
    "adaptive_validation_plots": "adaptive/round~{round}/validation/{model}",
    "adaptive_record": "adaptive/round~{round}/record.json",
    "learning_curve": "adaptive/learning_curve.csv",
    "learning_curve_plots": "adaptive/plots",
}
#: The workflow's results directory (relative to its working directory).
RESULTS = "results"


def log_pattern(rule: str) -> str:
    """``logs/{rule}/{scenario}/speed~{speed}_depth~{depth}.log``: a per-point job's log."""
    return f"logs/{rule}/{{scenario}}/{POINT_STEM}.log"


def pattern(kind: str, results: str | Path = RESULTS) -> str:
    """The path pattern of one kind of result (a key of :data:`PATHS`), with wildcards."""
    return f"{Path(results).as_posix()}/{PATHS[kind]}"


def _path(kind: str, results: str | Path, point: SweepPoint | None = None, **names: str) -> Path:
    """``results``/``PATHS[kind]`` filled with the point's numbers and ``names``, each of which
    (a scenario, a model) must be a plain name (:func:`~dozerlab.runtime.check_name`), so
    that no name leads outside ``results``."""
    for wildcard, value in names.items():
        check_name(value, wildcard)
    if point is not None:
        check_name(point.scenario, "scenario")
        names |= {
            "scenario": point.scenario,
            "speed": fmt_number(point.speed),
            "depth": fmt_number(point.depth),
        }
    return Path(results) / PATHS[kind].format(**names)


def bed_path(results: str | Path, scenario: str, ext: str = "npz") -> Path:
    """``results/beds/{scenario}.{ext}`` (the bed's npz or its png)."""
    if ext not in ("npz", "png"):
        raise ValueError(f"a bed is an npz or a png, not '{ext}'")
    return _path("bed" if ext == "npz" else "bed_plot", results, scenario=scenario)


def trajectory_path(results: str | Path, point: SweepPoint, ext: str = "csv") -> Path:
    """``results/trajectories/{scenario}/speed~{speed}_depth~{depth}.{ext}`` (csv or png)."""
    if ext not in ("csv", "png"):
        raise ValueError(f"a trajectory is a csv or a png, not '{ext}'")
    return _path("trajectory" if ext == "csv" else "trajectory_plot", results, point)


def field_path(results: str | Path, point: SweepPoint) -> Path:
    """``results/fields/{scenario}/speed~{speed}_depth~{depth}.zarr``."""
    return _path("field", results, point)


def simulate_benchmark_path(results: str | Path, point: SweepPoint) -> Path:
    """Snakemake's benchmark record (wall time, memory) of the point's simulation job."""
    return _path("simulate_benchmark", results, point)


def state_path(results: str | Path, point: SweepPoint) -> Path:
    """``results/states/{scenario}/speed~{speed}_depth~{depth}.npz``: NDEM's final particle state."""
    return _path("state", results, point)


def twin_path(results: str | Path, point: SweepPoint, ext: str = "zarr", draw: int = 1) -> Path:
    """``results/twins/{scenario}/speed~{speed}_depth~{depth}.{ext}``: the point's twin NDEM run
    (``reduced.twin``), its field store (``zarr``) or final state (``npz``); draw k ≥ 2 of
    ``reduced.twin.draws``: ``…_depth~{depth}_draw~{k}.{ext}``."""
    if ext not in ("zarr", "npz"):
        raise ValueError(f"a twin run is a zarr store or an npz state, not '{ext}'")
    if draw < 1:
        raise ValueError(f"twin draws count from 1, got {draw}")
    if draw == 1:
        return _path("twin" if ext == "zarr" else "twin_state", results, point)
    return _path(
        "twin_draw" if ext == "zarr" else "twin_draw_state", results, point, draw=str(draw)
    )


def twin_draws(results: str | Path, point: SweepPoint, draws: int) -> list[tuple[Path, Path]]:
    """The (store, final state) of each of the point's ``draws`` twin runs, draw 1 first."""
    return [
        (twin_path(results, point, "zarr", k), twin_path(results, point, "npz", k))
        for k in range(1, draws + 1)
    ]


def reduced_path(
    results: str | Path, dynamics_model: str, point: SweepPoint, ext: str = "zarr"
) -> Path:
    """``results/reduced/{dynamics_model}/{scenario}/speed~{speed}_depth~{depth}.{ext}``.

    ``zarr``: the reduced run's field store; ``npz``: its final particle state (a bed file).
    """
    if ext not in ("zarr", "npz"):
        raise ValueError(f"a reduced run is a zarr store or an npz state, not '{ext}'")
    kind = "reduced" if ext == "zarr" else "reduced_state"
    return _path(kind, results, point, dynamics_model=dynamics_model)


def _per_model(kind: str, what: str) -> Callable[[str | Path, str], Path]:
    """The path function ``(results, model) -> Path`` of a result kept per model (``what`` it
    is): the template ``PATHS[kind]`` with its one wildcard (``{model}`` or ``{dynamics_model}``)
    filled."""
    (wildcard,) = (name for _, name, _, _ in Formatter().parse(PATHS[kind]) if name)

    def path(results: str | Path, model: str) -> Path:
        return _path(kind, results, None, **{wildcard: model})

    path.__name__ = f"{kind}_path"
    path.__doc__ = f"``results/{PATHS[kind]}``: {what}."
    return path


reduced_comparison_path = _per_model("reduced_comparison", "the reduced runs measured against NDEM")
loop_force_model_path = _per_model(
    "loop_force_model",
    "the force model trained on that dynamics model's loop fields (an MLflow pyfunc directory)",
)
reduce_benchmark_path = _per_model(
    "reduce_benchmark",
    "Snakemake's benchmark record of that dynamics model's runs of the held-out points (one job)",
)
reduce_training_benchmark_path = _per_model(
    "reduce_training_benchmark",
    "Snakemake's benchmark record of that dynamics model's runs of the training points (one job)",
)
model_path = _per_model("model", "an MLflow pyfunc model directory")
validation_path = _per_model("validation", "held-out metrics of one model")
dynamics_model_path = _per_model("dynamics_model", "an evolution model's MLflow pyfunc directory")
dynamics_validation_path = _per_model("dynamics_validation", "an evolution model's held-out errors")
dynamics_plots_path = _per_model("dynamics_plots", "the figures of that validation")


def reduce_force_model_path(
    results: str | Path, reduced: dict[str, Any], dynamics_model: str
) -> Path:
    """The force model a dynamics model's reduced runs read, as rule ``reduce`` gives it:
    with ``reduced.force_fields`` loop the one fitted to that model's loop fields
    (:func:`loop_force_model_path`), but for replay (its fields are NDEM's); else
    ``results/models/{reduced.force_model}``. ``reduced``: the config's ``reduced`` section."""
    if reduced["force_fields"] == "ndem" or dynamics_model == "replay":
        return model_path(results, reduced["force_model"])
    return loop_force_model_path(results, dynamics_model)


def adaptive_path(kind: str, results: str | Path, round_index: int, model: str = "") -> Path:
    """A round's file of an adaptive sweep: ``kind`` one of the ``adaptive_*`` keys of
    :data:`PATHS` (``model`` for a round's model and validation)."""
    if not kind.startswith("adaptive_"):
        raise ValueError(f"'{kind}' is not a round's file of an adaptive sweep")
    names = {"model": model} if "{model}" in PATHS[kind] else {}
    return _path(kind, results, None, round=str(int(round_index)), **names)
