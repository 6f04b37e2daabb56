"""An evolution model as an MLflow pyfunc model directory, and loading it back.

Contract (docs/models.md, "Field-evolution models")::

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

from pathlib import Path
from typing import Any

import numpy as np
import torch

from dozerlab.learn.dynamics.models import DynamicsModel
from dozerlab.learn.pyfunc import (
    INPUT_NAMES,
    PyfuncFormat,
    model_dir_kind,
    python_model_class,
    require_inputs,
)
from dozerlab.runtime import DozerlabError

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
        tuple(meta.get("y_bands", ())),
        tuple(meta.get("z_bands", ())),
        bool(meta.get("momentum", False)),
    )
    model.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
    return model.eval()


@torch.no_grad()
def predict_arrays(model: DynamicsModel, arrays: Any, batch: int = 64) -> dict[str, np.ndarray]:
    """The next m rows' ``velocity`` (B, m, X, Y, Z, 3) and ``density`` (B, m, X, Y, Z) as
    float32 arrays, from the input dict of the contract (shapes checked)."""
    require_inputs(arrays)
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


def _extras(model: DynamicsModel, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    return {
        "signature": signature(model),
        "input_example": example(model, arrays),
        "metadata": {"history": model.history, "horizon": model.horizon, "kind": model.kind},
    }


def _check(meta: dict[str, Any], path: str | Path) -> None:
    if "horizon" not in meta:
        raise DozerlabError(f"{path} is a force model, not an evolution model (no horizon)")


#: What ``dozerlab train-dynamics`` writes; only an earlier evolution model may be replaced.
MODEL_DIR = model_dir_kind(
    "a dozerlab evolution model directory (written by train-dynamics)", "train-dynamics", True
)
#: The evolution models' pyfunc directories.
FORMAT = PyfuncFormat(
    "dozerlab evolution model",
    Path(__file__).with_name("pyfunc_entry.py"),
    build,
    _extras,
    "DynamicsPyfunc",
    predict_arrays,
    _check,
)
save, load = FORMAT.save, FORMAT.load


def __getattr__(name: str) -> Any:
    # ``DynamicsPyfunc``: what pyfunc_entry.py sets, made when MLflow's loader runs it.
    if name == FORMAT.class_name:
        return python_model_class(FORMAT)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
