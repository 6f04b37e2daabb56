"""The train / validate / evaluate jobs: files in, files out, each an MLflow run."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab import tracking
from dozerlab.learn import pyfunc
from dozerlab.learn.data import StoreData, check_grid, load_store, point_key
from dozerlab.learn.metrics import flat
from dozerlab.learn.plots import loss_curves
from dozerlab.learn.train import EpochCallback, TrainResult, train_model
from dozerlab.learn.validate import evaluate, load_groups, strip_series, validate
from dozerlab.runtime import OutputKind, atomic_output, check_output, json_with

#: What ``validate`` writes beside its plots: the metrics JSON.
VALIDATION_JSON = OutputKind(
    "a dozerlab validation JSON", json_with(("model", "groups", "overall", "summary"))
)


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


def epoch_logger(run: Any, val_name: str) -> EpochCallback | None:
    """An ``on_epoch`` callback logging ``train_loss`` and ``val_name`` to the active MLflow
    run (None without a run)."""
    if run is None:
        return None
    import mlflow

    def log_epoch(epoch: int, tr: float, va: float) -> None:
        mlflow.log_metrics({"train_loss": tr, val_name: va}, step=epoch)

    return log_epoch


def store_arrays(store: StoreData) -> dict[str, np.ndarray]:
    """The store's per-row model inputs: velocity, density, blade_velocity."""
    return {
        "velocity": store.velocity,
        "density": store.density,
        "blade_velocity": store.blade_velocity,
    }


def train_job(
    kind: str,
    train: list[str | Path],
    config: dict[str, Any],
    out: str | Path,
    device: str | None = None,
    progress: bool = True,
) -> TrainResult:
    """Train ``kind`` on the stores ``train``; save the MLflow model directory at ``out`` and
    log the run (params, per-epoch losses, final training metrics, loss plot, model)."""
    import mlflow

    check_output(out, pyfunc.MODEL_DIR)  # refuse a wrong --out before training, not after
    stores = [load_store(p) for p in train]
    check_grid(stores)  # counts and sizes of the bins agree
    meta = {**training_meta(stores, train), "learn": config["learn"], "seed": config.get("seed")}
    params = {
        "model": kind,
        "seed": config.get("seed"),
        "learn": config["learn"],
        "train_stores": ",".join(str(p) for p in train),
    }
    with tracking.job_run(
        config, f"train {kind}", rule="train", tags={"model": kind}, params=params
    ) as run:
        log_epoch = epoch_logger(run, "val_loss")
        result = train_model(
            kind, stores, config, device=device, on_epoch=log_epoch, progress=progress
        )
        meta.update(result_meta(result))
        model = result.model.cpu()
        example = store_arrays(stores[0])
        with atomic_output(out, pyfunc.MODEL_DIR) as tmp:
            pyfunc.save(model, meta, tmp, example)
        if run is not None:
            fit = evaluate(model, stores)["overall"]
            mlflow.log_metrics(
                {
                    **flat(fit, "train"),
                    "best_val_loss": min(result.val_loss),
                    "best_epoch": result.best_epoch,
                    "train_seconds": result.seconds,
                }
            )
            with tempfile.TemporaryDirectory() as d:
                mlflow.log_artifact(
                    str(loss_curves(result.train_loss, result.val_loss, Path(d) / "loss.png", kind))
                )
            result.model_uri = pyfunc.log(model, meta, example).model_uri
    return result


def validate_job(
    model_dir: str | Path,
    interpolation: list[str | Path],
    extrapolation: list[str | Path],
    out: str | Path,
    plots_dir: str | Path | None = None,
    config: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Validate a saved model on held-out stores: JSON at ``out``, plots (default: a folder
    named after ``out``) and an MLflow validate run."""
    import mlflow

    out = Path(out)
    check_output(out, VALIDATION_JSON)
    model, meta = pyfunc.load(model_dir)
    pdir = Path(plots_dir) if plots_dir else out.with_suffix("")
    groups = load_groups(interpolation, extrapolation)
    params = {
        "model_dir": str(model_dir),
        "interpolation": ",".join(map(str, interpolation)),
        "extrapolation": ",".join(map(str, extrapolation)),
    }
    with tracking.job_run(
        config, f"validate {model.kind}", rule="validate", tags={"model": model.kind}, params=params
    ) as run:
        result = validate(model, meta, groups, pdir, out.parent)
        with atomic_output(out, VALIDATION_JSON) as tmp:
            tmp.write_text(json.dumps(result, indent=1))
        if run is not None:
            metrics = flat(result["overall"], "overall")
            for g, data in result["groups"].items():
                metrics.update(flat(data["overall"], g))
            mlflow.log_metrics(metrics)
            mlflow.log_artifact(str(out))
            mlflow.log_artifacts(str(pdir), artifact_path="plots")
    return result


def evaluate_job(model_dir: str | Path, stores: list[str | Path]) -> dict[str, Any]:
    """Metrics of a saved model on ``stores`` (per store and overall)."""
    model, meta = pyfunc.load(model_dir)
    data = [load_store(p) for p in stores]
    check_grid(data, model.grid, meta.get("bin_size"))
    result = evaluate(model, data)
    result["points"] = strip_series(result["points"])
    return result
