"""The trained model as an MLflow pyfunc model directory, and loading it back.

Contract for users' scripts::

    m = mlflow.pyfunc.load_model("results/models/unet")
    m.predict({"velocity": (B, Nx, Ny, Nz, 3), "density": (B, Nx, Ny, Nz), "blade_velocity": (B, 3)})
    # -> DataFrame, columns force_x … torque_z, in N and N·m

Inputs are float32 arrays straight from a field store; normalisation lives inside the model.
With ``learn.history`` H > 1 the B rows are taken as consecutive steps of one run, and the
first H-1 rows, which lack a full history, repeat their earliest available step.

The directory holds ``artifacts/weights.pt`` (a state dict, loaded with ``weights_only=True``)
and ``artifacts/meta.json`` (architecture, grid, training points, loss history).
"""

from __future__ import annotations

import contextlib
import json
import tempfile
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import mlflow
import numpy as np
import pandas as pd
import torch
from mlflow.pyfunc.model import PythonModel

from dozerlab.learn.data import TARGET_NAMES
from dozerlab.learn.models import ForceModel
from dozerlab.runtime import DozerlabError, OutputKind

INPUT_NAMES = ("velocity", "density", "blade_velocity")


def is_model_dir(path: Path) -> bool:
    """An MLflow model directory holding this package's ``artifacts/meta.json`` and weights."""
    art = path / "artifacts"
    return (
        (path / "MLmodel").is_file()
        and (art / "weights.pt").is_file()
        and "kind" in json.loads((art / "meta.json").read_text())
    )


#: What ``dozerlab train`` writes; an earlier model of ours at ``--out`` may be replaced.
MODEL_DIR = OutputKind("a dozerlab model directory (MLmodel + artifacts/meta.json)", is_model_dir)


def build(meta: dict[str, Any], weights: str | Path) -> ForceModel:
    """Rebuild a :class:`ForceModel` from its metadata and state-dict file (CPU, eval mode)."""
    model = ForceModel(meta["kind"], tuple(meta["grid"]), meta["history"])
    model.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
    return model.eval()


def with_history(arrays: dict[str, np.ndarray], history: int) -> tuple[torch.Tensor, ...]:
    """Per-step arrays (B, …) → tensors with a history axis (B, H, …) over consecutive rows."""
    b = arrays["density"].shape[0]
    rows = np.clip(np.arange(b)[:, None] + np.arange(1 - history, 1)[None, :], 0, None)
    return tuple(
        torch.from_numpy(np.ascontiguousarray(arrays[k], dtype=np.float32)[rows])
        for k in INPUT_NAMES
    )


def check_inputs(arrays: Any, grid: tuple[int, int, int]) -> dict[str, np.ndarray]:
    """The three input arrays, shape-checked against the model's grid."""
    if not isinstance(arrays, dict):
        raise DozerlabError(
            f"model input must be a dict with keys {list(INPUT_NAMES)}, got {type(arrays).__name__}"
        )
    missing = [k for k in INPUT_NAMES if k not in arrays]
    if missing:
        raise DozerlabError(f"model input lacks {missing}; it needs {list(INPUT_NAMES)}")
    out = {k: np.asarray(arrays[k], dtype=np.float32) for k in INPUT_NAMES}
    b = out["density"].shape[0] if out["density"].ndim else 0
    expected = {"velocity": (b, *grid, 3), "density": (b, *grid), "blade_velocity": (b, 3)}
    for k, shape in expected.items():
        if out[k].shape != shape:
            raise DozerlabError(
                f"model input '{k}' has shape {out[k].shape}, expected {shape}: the model was trained on a "
                f"{grid} grid (sampling.bins)"
            )
    return out


@torch.no_grad()
def predict_arrays(
    model: ForceModel, arrays: dict[str, np.ndarray], batch: int = 256
) -> np.ndarray:
    """(B, 6) float32 force (N) and torque (N·m) of per-step input arrays."""
    arrays = check_inputs(arrays, model.grid)
    v, rho, vb = with_history(arrays, model.history)
    dev = next(model.buffers()).device
    out = [
        model(v[i : i + batch].to(dev), rho[i : i + batch].to(dev), vb[i : i + batch].to(dev)).cpu()
        for i in range(0, v.shape[0], batch)
    ]
    return torch.cat(out).numpy() if out else np.zeros((0, 6), np.float32)


# No type hints on predict: MLflow would read them as a competing input schema (the signature
# already states it). It warns about their absence when the class is defined, in every job and
# script that loads a model, under a filter of its own, so the warning is caught, not filtered.
@contextlib.contextmanager
def untyped_predict() -> Iterator[None]:
    """Define a PythonModel with an untyped ``predict`` inside: MLflow's request for type hints
    is dropped, every other warning passes."""
    with warnings.catch_warnings(record=True) as caught:
        yield
    for w in caught:
        if "Add type hints to the `predict` method" not in str(w.message):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


with untyped_predict():

    class ForcePyfunc(PythonModel):
        """MLflow pyfunc wrapper around a :class:`ForceModel`."""

        def load_context(self, context: Any) -> None:
            meta = json.loads(Path(context.artifacts["meta"]).read_text())
            self.model = build(meta, context.artifacts["weights"])

        def predict(self, context, model_input, params=None):
            """(B, 6) DataFrame force_x … torque_z (N, N·m) of a dict of per-step input arrays."""
            return pd.DataFrame(predict_arrays(self.model, model_input), columns=list(TARGET_NAMES))


def signature(grid: tuple[int, int, int]) -> Any:
    """Named-tensor input schema (batch axis -1) and the six output columns."""
    from mlflow.models import ModelSignature
    from mlflow.types import ColSpec, Schema, TensorSpec

    f32 = np.dtype(np.float32)
    inputs = Schema(
        [
            TensorSpec(f32, (-1, *grid, 3), "velocity"),
            TensorSpec(f32, (-1, *grid), "density"),
            TensorSpec(f32, (-1, 3), "blade_velocity"),
        ]
    )
    return ModelSignature(
        inputs=inputs, outputs=Schema([ColSpec("float", c) for c in TARGET_NAMES])
    )


def pip_requirements() -> list[str]:
    """Pinned requirements of a saved model (explicit: MLflow's inference of them is slow)."""
    from importlib.metadata import version

    return [f"{p}=={version(p)}" for p in ("mlflow", "torch", "numpy", "pandas", "dozerlab")]


def model_kwargs(
    model: ForceModel, meta: dict[str, Any], workdir: Path, example: dict[str, np.ndarray]
) -> dict[str, Any]:
    """Arguments shared by ``mlflow.pyfunc.save_model`` and ``log_model`` (files go to ``workdir``)."""
    return {
        # Models from code: loading runs this package's entry file instead of unpickling an object.
        "python_model": str(Path(__file__).with_name("pyfunc_entry.py")),
        "artifacts": write_artifacts(model, meta, workdir),
        "signature": signature(model.grid),
        "input_example": {
            k: np.ascontiguousarray(example[k][:1], dtype=np.float32) for k in INPUT_NAMES
        },
        "pip_requirements": pip_requirements(),
    }


def write_artifacts(model: Any, meta: dict[str, Any], workdir: Path) -> dict[str, str]:
    """``weights.pt`` (the state dict) and ``meta.json`` (``meta`` and ``model.spec()``) in
    ``workdir``: a model directory's MLflow artifacts."""
    weights, meta_path = workdir / "weights.pt", workdir / "meta.json"
    torch.save({k: v.detach().cpu() for k, v in model.state_dict().items()}, weights)
    meta_path.write_text(json.dumps({**meta, **model.spec()}, indent=1))
    return {"weights": str(weights), "meta": str(meta_path)}


def read_artifacts(path: str | Path, what: str = "dozerlab model") -> tuple[dict[str, Any], Path]:
    """The metadata and weights file of a saved model directory (FileNotFoundError if absent)."""
    art = Path(path) / "artifacts"
    if not (art / "meta.json").is_file() or not (art / "weights.pt").is_file():
        raise FileNotFoundError(
            f"not a {what} directory (no artifacts/meta.json, weights.pt): {path}"
        )
    return json.loads((art / "meta.json").read_text()), art / "weights.pt"


def save_model(path: str | Path, kwargs: Callable[[Path], dict[str, Any]]) -> None:
    """``mlflow.pyfunc.save_model`` at ``path`` with ``kwargs(workdir)`` (files made there)."""
    with tempfile.TemporaryDirectory() as tmp:
        mlflow.pyfunc.save_model(path=str(path), **kwargs(Path(tmp)))


def log_model(kwargs: Callable[[Path], dict[str, Any]]) -> Any:
    """``mlflow.pyfunc.log_model`` to the active run as the model named ``model``."""
    with tempfile.TemporaryDirectory() as tmp:
        return mlflow.pyfunc.log_model(name="model", **kwargs(Path(tmp)))


def save(
    model: ForceModel, meta: dict[str, Any], path: str | Path, example: dict[str, np.ndarray]
) -> None:
    """Save ``model`` as an MLflow pyfunc directory at ``path`` (which must not exist)."""
    save_model(path, lambda tmp: model_kwargs(model, meta, tmp, example))


def log(model: ForceModel, meta: dict[str, Any], example: dict[str, np.ndarray]) -> Any:
    """Log ``model`` to the active MLflow run as the model named ``model``."""
    return log_model(lambda tmp: model_kwargs(model, meta, tmp, example))


def load(path: str | Path) -> tuple[ForceModel, dict[str, Any]]:
    """Load a saved model directory directly (no MLflow runtime): the model and its metadata."""
    meta, weights = read_artifacts(path)
    return build(meta, weights), meta
