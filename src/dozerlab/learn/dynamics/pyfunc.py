"""An evolution model as an MLflow pyfunc model directory, and loading it back.

Contract (README "Field-evolution models")::

    m = mlflow.pyfunc.load_model("results/dynamics/ridge")
    H, m_ = m.metadata.metadata["history"], m.metadata.metadata["horizon"]
    out = m.predict({"velocity": (B, H, Nx, Ny, Nz, 3), "density": (B, H, Nx, Ny, Nz),
                     "blade_velocity": (B, H + m_, 3)})
    # -> {"velocity": (B, m_, Nx, Ny, Nz, 3) m/s, "density": (B, m_, Nx, Ny, Nz) kg/m³}

float32 arrays as they come from a store, rows oldest first; the blade velocity covers the H
known rows and the m rows to predict. Normalisation is inside the model. The directory holds
``artifacts/weights.pt`` (a state dict, loaded with ``weights_only=True``) and
``artifacts/meta.json`` (architecture, frame, training points, losses).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from mlflow.pyfunc.model import PythonModel

from dozerlab.learn.dynamics.models import DynamicsModel
from dozerlab.learn.pyfunc import (
    log_model,
    pip_requirements,
    read_artifacts,
    save_model,
    untyped_predict,
    write_artifacts,
)
from dozerlab.runtime import DozerlabError

INPUT_NAMES = ("velocity", "density", "blade_velocity")
OUTPUT_NAMES = ("velocity", "density")


def build(meta: dict[str, Any], weights: str | Path) -> DynamicsModel:
    """Rebuild a :class:`DynamicsModel` from its metadata and state-dict file (CPU, eval mode)."""
    model = DynamicsModel(
        meta["kind"],
        tuple(meta["grid"]),
        meta["history"],
        meta["horizon"],
        meta["row_dt"],
        tuple(meta["bin_size"]),
        meta.get("width", 8),
    )
    model.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
    return model.eval()


@torch.no_grad()
def predict_arrays(model: DynamicsModel, arrays: Any, batch: int = 64) -> dict[str, np.ndarray]:
    """The next m rows' ``velocity`` (B, m, X, Y, Z, 3) and ``density`` (B, m, X, Y, Z) as
    float32 arrays, from the input dict of the contract (shapes checked)."""
    if not isinstance(arrays, dict):
        raise DozerlabError(
            f"model input must be a dict with keys {list(INPUT_NAMES)}, got {type(arrays).__name__}"
        )
    missing = [k for k in INPUT_NAMES if k not in arrays]
    if missing:
        raise DozerlabError(f"model input lacks {missing}; it needs {list(INPUT_NAMES)}")
    v, rho, vb = (
        torch.from_numpy(np.ascontiguousarray(arrays[k], np.float32)) for k in INPUT_NAMES
    )
    model.check(v, rho, vb)
    dev = next(model.buffers()).device
    outs = [
        model(v[i : i + batch].to(dev), rho[i : i + batch].to(dev), vb[i : i + batch].to(dev))
        for i in range(0, v.shape[0], batch)
    ]
    if not outs:
        shape = (0, model.horizon, *model.grid)
        return {
            "velocity": np.zeros((*shape, 3), np.float32),
            "density": np.zeros(shape, np.float32),
        }
    return {
        name: torch.cat([o[i] for o in outs]).cpu().numpy() for i, name in enumerate(OUTPUT_NAMES)
    }


with untyped_predict():

    class DynamicsPyfunc(PythonModel):
        """MLflow pyfunc wrapper around a :class:`DynamicsModel`."""

        def load_context(self, context: Any) -> None:
            meta = json.loads(Path(context.artifacts["meta"]).read_text())
            self.model = build(meta, context.artifacts["weights"])

        def predict(self, context, model_input, params=None):
            """The contract's output dict of the contract's input dict."""
            return predict_arrays(self.model, model_input)


def signature(model: DynamicsModel) -> Any:
    """Named-tensor input and output schema (batch axis -1)."""
    from mlflow.models import ModelSignature
    from mlflow.types import Schema, TensorSpec

    f32, g, h, m = np.dtype(np.float32), model.grid, model.history, model.horizon
    return ModelSignature(
        inputs=Schema(
            [
                TensorSpec(f32, (-1, h, *g, 3), "velocity"),
                TensorSpec(f32, (-1, h, *g), "density"),
                TensorSpec(f32, (-1, h + m, 3), "blade_velocity"),
            ]
        ),
        outputs=Schema(
            [TensorSpec(f32, (-1, m, *g, 3), "velocity"), TensorSpec(f32, (-1, m, *g), "density")]
        ),
    )


def example(model: DynamicsModel, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The first window of per-row store arrays (T, …) in the contract's shapes (batch 1)."""
    h, m = model.history, model.horizon
    return {
        "velocity": np.ascontiguousarray(arrays["velocity"][None, :h], np.float32),
        "density": np.ascontiguousarray(arrays["density"][None, :h], np.float32),
        "blade_velocity": np.ascontiguousarray(arrays["blade_velocity"][None, : h + m], np.float32),
    }


def _kwargs(
    model: DynamicsModel, meta: dict[str, Any], workdir: Path, arrays: dict[str, np.ndarray]
) -> dict[str, Any]:
    return {
        # Models from code: loading runs this package's entry file instead of unpickling an object.
        "python_model": str(Path(__file__).with_name("pyfunc_entry.py")),
        "artifacts": write_artifacts(model, meta, workdir),
        "signature": signature(model),
        "input_example": example(model, arrays),
        "pip_requirements": pip_requirements(),
        "metadata": {"history": model.history, "horizon": model.horizon, "kind": model.kind},
    }


def save(
    model: DynamicsModel, meta: dict[str, Any], path: str | Path, arrays: dict[str, np.ndarray]
) -> None:
    """Save ``model`` as an MLflow pyfunc directory at ``path`` (which must not exist);
    ``arrays`` are per-row store arrays for the input example."""
    save_model(path, lambda tmp: _kwargs(model, meta, tmp, arrays))


def log(model: DynamicsModel, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> Any:
    """Log ``model`` to the active MLflow run as the model named ``model``."""
    return log_model(lambda tmp: _kwargs(model, meta, tmp, arrays))


def load(path: str | Path) -> tuple[DynamicsModel, dict[str, Any]]:
    """Load a saved evolution model directory directly (no MLflow runtime): model and metadata."""
    meta, weights = read_artifacts(path, "dozerlab evolution model")
    if "horizon" not in meta:
        raise DozerlabError(f"{path} is a force model, not an evolution model (no horizon)")
    return build(meta, weights), meta
