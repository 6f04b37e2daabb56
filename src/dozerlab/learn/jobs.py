"""The train / validate / evaluate jobs: files in, files out, each an MLflow run."""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab import tracking
from dozerlab.learn import pyfunc
from dozerlab.learn.data import StoreData, check_grid, load_store, point_key, with_loop_fields
from dozerlab.learn.fitting import device_for
from dozerlab.learn.metrics import flat
from dozerlab.learn.plots import loss_curves
from dozerlab.learn.pyfunc import MODEL_DIR
from dozerlab.learn.train import EpochCallback, TrainResult, train_model
from dozerlab.learn.validate import evaluate, load_groups, strip_series, validate
from dozerlab.runtime import (
    DozerlabError,
    OutputKind,
    atomic_output,
    job_outputs,
    json_with,
    keep_freed_memory,
    marked_folder,
)
from dozerlab.tracking import JobRun

#: What ``validate`` writes beside its plots: the metrics JSON.
VALIDATION_JSON = OutputKind(
    "a dozerlab validation JSON",
    json_with(("model", "groups", "overall", "summary"), without=("horizon",)),
    "validate",
)
#: ``validate``'s plots: a folder built whole (the JSON's plot paths point into it).
VALIDATION_PLOTS = marked_folder("a dozerlab folder of validation plots", "validation-plots")


def training_meta(stores: list[StoreData], train: list[str | Path]) -> dict[str, Any]:
    """What a trained model records of its training points (validation refuses them)."""
    return {
        "train_points": [s.point for s in stores],
        "train_keys": [k for s in stores if (k := point_key(s.point)) is not None],
        "train_sources": [str(Path(p).resolve()) for p in train],
        "bin_size": next((list(s.bin_size) for s in stores if s.bin_size is not None), None),
    }


def result_meta(result: TrainResult) -> dict[str, Any]:
    """A training's losses, best epoch, sample counts and time, for the model's metadata."""
    return {
        "train_loss": result.train_loss,
        "val_loss": result.val_loss,
        "best_epoch": result.best_epoch,
        "samples": result.samples,
        "seconds": result.seconds,
    }


def epoch_logger(run: JobRun | None, val_name: str) -> EpochCallback | None:
    """An ``on_epoch`` callback logging ``train_loss`` and ``val_name`` to the active MLflow
    run (None without a run)."""
    if run is None:
        return None

    def log_epoch(epoch: int, tr: float, va: float) -> None:
        run.log_metrics({"train_loss": tr, val_name: va}, step=epoch)

    return log_epoch


def store_arrays(store: StoreData) -> dict[str, np.ndarray]:
    """The store's per-row model inputs: velocity, density, blade_velocity."""
    return {
        "velocity": store.velocity,
        "density": store.density,
        "blade_velocity": store.blade_velocity,
    }


@dataclass(frozen=True)
class Family:
    """What the training job of one family of models (the force models, the evolution models)
    is made of; :func:`train_job` does the rest, the same for every family.

    ``title`` prefixes run names and plot titles (``""``, ``"dynamics "``); ``rule`` is the
    workflow rule (the run's ``rule`` tag); ``val_metric`` names the validation loss among the
    per-epoch metrics; ``fit(kind, stores, config, **FitOptions)`` trains; ``pyfunc`` writes the
    model directory; ``recorded(config)`` gives the config parts recorded in the model's
    metadata and in the run's params; ``fit_metrics(model, stores)`` adds metrics on the
    training stores to the run. ``output`` is the kind of model directory the family's
    command writes; ``family`` (``force``, ``evolution``) names the family in run
    names and Model Registry names (:func:`dozerlab.tracking.registered_name`).
    """

    title: str
    rule: str
    val_metric: str
    fit: Callable[..., TrainResult]
    pyfunc: pyfunc.PyfuncFormat
    recorded: Callable[[dict[str, Any]], tuple[dict[str, Any], dict[str, Any]]]
    fit_metrics: Callable[[Any, list[StoreData]], dict[str, float]] = lambda model, stores: {}
    output: OutputKind = MODEL_DIR
    family: str = "force"


def _force_recorded(config: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    return {"learn": config["learn"]}, {"learn": config["learn"]}


#: The force models: ``dozerlab train``.
FORCE = Family(
    "",
    "train",
    "val_loss",
    train_model,
    pyfunc.FORMAT,
    _force_recorded,
    lambda model, stores: flat(evaluate(model, stores)["overall"], "train"),
)


def train_job(
    kind: str,
    train: list[str | Path],
    config: dict[str, Any],
    out: str | Path,
    device: str | None = None,
    progress: bool = True,
    family: Family = FORCE,
    loop_fields: list[str | Path] | None = None,
) -> TrainResult:
    """Train model ``kind`` of ``family`` on the stores ``train``; save the MLflow model
    directory at ``out`` and log the run (params, per-epoch losses, final training metrics,
    loss plot, model).

    ``loop_fields`` (force models only): the reduced loop's runs of the same points, one per
    store of ``train`` in the same order, whose velocity and density replace NDEM's
    (:func:`~dozerlab.learn.data.with_loop_fields`): the force model of the reduced loop,
    the workflow's rule ``train_loop_force``.
    """
    with job_outputs(("--out", out, family.output)):  # a wrong --out fails before training
        device_for(device)  # and a device this machine lacks
        keep_freed_memory()  # the batches' large blocks reused, not faulted in afresh
        return _train(kind, train, config, out, device, progress, family, loop_fields)


def _train(
    kind: str,
    train: list[str | Path],
    config: dict[str, Any],
    out: str | Path,
    device: str | None,
    progress: bool,
    family: Family,
    loop_fields: list[str | Path] | None,
) -> TrainResult:
    stores = [load_store(p) for p in train]
    rule, tags = family.rule, {"model": kind}
    if loop_fields:
        if family is not FORCE:
            raise DozerlabError("only force models are trained on the reduced loop's fields")
        if len(loop_fields) != len(train):
            raise DozerlabError(
                f"{len(loop_fields)} loop-field stores for {len(train)} training stores: "
                "give one reduced run per training store, in the same order"
            )
        stores = [
            with_loop_fields(s, load_store(f)) for s, f in zip(stores, loop_fields, strict=True)
        ]
        rule, tags = "train_loop_force", tags | {"fields": "loop"}
        if dynamics_model := loop_dynamics_model(loop_fields[0]):
            tags["dynamics_model"] = dynamics_model
    check_grid(stores)  # counts and sizes of the bins agree
    seed = config.get("seed")
    meta_parts, param_parts = family.recorded(config)
    meta = {**training_meta(stores, train), **meta_parts, "seed": seed}
    params = {"model": kind, "seed": seed, **param_parts}
    params["train_stores"] = ",".join(str(p) for p in train)
    if loop_fields:
        meta["loop_fields"] = [str(Path(p).resolve()) for p in loop_fields]
        params["loop_fields"] = ",".join(str(p) for p in loop_fields)
    name = f"{family.title}{kind}" + (" on the loop's fields" if loop_fields else "")
    # the loop's force model: <kind>-loop-<dynamics model>, not to be confused with <kind>
    model_name = (
        "-".join([kind, "loop", tags.get("dynamics_model", "")]).strip("-") if loop_fields else kind
    )
    run_name = tracking.run_name("train", family.family, model_name)
    with tracking.job_run(config, run_name, rule=rule, tags=tags, params=params) as run:
        log_epoch = epoch_logger(run, family.val_metric)
        result = family.fit(
            kind, stores, config, device=device, on_epoch=log_epoch, progress=progress
        )
        meta.update(result_meta(result))
        model = result.model.cpu()
        example = store_arrays(stores[0])
        with atomic_output(out, family.output) as tmp:
            family.pyfunc.save(model, meta, tmp, example)
        if run is not None:
            run.log_metrics(
                {
                    **family.fit_metrics(model, stores),
                    f"best_{family.val_metric}": min(result.val_loss),
                    "best_epoch": result.best_epoch,
                    "train_seconds": result.seconds,
                    **({} if result.penalty is None else {"penalty": result.penalty}),
                }
            )
            with tempfile.TemporaryDirectory() as d:
                png = loss_curves(result.train_loss, result.val_loss, Path(d) / "loss.png", name)
                run.log_artifact(png)
            registered = tracking.registered_name(config, family.family, model_name)
            result.model_uri = run.log_model(out, registered)
    return result


def loop_dynamics_model(store: str | Path) -> str:
    """The dynamics model whose reduced loop wrote ``store`` (its ``dynamics_model`` attribute),
    "" if the store does not say."""
    from dozerlab.fields.store import open_store

    return str(open_store(store).attrs.get("dynamics_model", ""))


def held_out_params(
    model_dir: str | Path,
    interpolation: list[str | Path],
    extrapolation: list[str | Path],
    transfer: list[str | Path] | tuple[()] = (),
) -> dict[str, Any]:
    """A validation run's params: the model directory and the held-out stores (the transfer
    group's only where it has any)."""
    params = {
        "model_dir": str(model_dir),
        "interpolation": ",".join(map(str, interpolation)),
        "extrapolation": ",".join(map(str, extrapolation)),
    }
    if transfer:
        params["transfer"] = ",".join(map(str, transfer))
    return params


def record_validation(
    run: JobRun | None,
    result: dict[str, Any],
    out: Path,
    kind: OutputKind,
    metrics: dict[str, float],
    plots_dir: Path,
) -> None:
    """Write a validation's ``result`` as JSON at ``out`` and, in an MLflow ``run``, log its
    ``metrics``, the JSON and the plots of ``plots_dir``."""
    with atomic_output(out, kind) as tmp:
        tmp.write_text(json.dumps(result, indent=1))
    if run is not None:
        run.log_metrics(metrics)
        run.log_artifact(out)
        run.log_artifacts(plots_dir, artifact_path="plots")


def validate_job(
    model_dir: str | Path,
    interpolation: list[str | Path],
    extrapolation: list[str | Path],
    out: str | Path,
    plots_dir: str | Path | None = None,
    config: dict[str, Any] | None = None,
    transfer: list[str | Path] | tuple[()] = (),
) -> dict[str, Any]:
    """Validate a saved model on held-out stores (``transfer``: those on unseen terrain): JSON at ``out``, plots (default: a folder
    named after ``out``, built whole: :data:`VALIDATION_PLOTS`) and an MLflow validate run.
    Both outputs are checked before any work; a failure leaves neither."""
    out = Path(out)
    pdir = Path(plots_dir) if plots_dir else out.with_suffix("")
    with job_outputs(("--out", out, VALIDATION_JSON), ("--plots", pdir, VALIDATION_PLOTS)):
        model, meta = pyfunc.load(model_dir)
        groups = load_groups(interpolation, extrapolation, transfer)
        params = held_out_params(model_dir, interpolation, extrapolation, transfer)
        with tracking.job_run(
            config,
            tracking.run_name("validate", FORCE.family, model.kind),
            rule="validate",
            tags={"model": model.kind},
            params=params,
        ) as run:
            with atomic_output(pdir, VALIDATION_PLOTS) as tmp:
                tmp.mkdir()
                result = validate(model, meta, groups, tmp, out.parent, plots_at=pdir)
            metrics = flat(result["overall"], "overall")
            for g, data in result["groups"].items():
                metrics.update(flat(data["overall"], g))
            record_validation(run, result, out, VALIDATION_JSON, metrics, pdir)
    return result


def evaluate_job(model_dir: str | Path, stores: list[str | Path]) -> dict[str, Any]:
    """Metrics of a saved model on ``stores`` (per store and overall)."""
    model, meta = pyfunc.load(model_dir)
    data = [load_store(p) for p in stores]
    check_grid(data, model.grid, meta.get("bin_size"), blade_part=model.blade_part)
    result = evaluate(model, data)
    result["points"] = strip_series(result["points"])
    return result
