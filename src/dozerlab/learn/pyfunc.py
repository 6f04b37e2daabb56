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

Every byte is checked on loading: at saving, ``meta.json`` records the SHA-256 of every other
file of the directory (``files_sha256``, by path relative to it) and of its own content
(``meta_sha256``, canonical JSON without that key); :func:`verify_model_dir` compares them and
refuses a changed, cut-short or missing file by name before torch reads a byte. A directory
saved before these digests existed is refused with the remedy (re-run ``dozerlab train``): its
files cannot be told from damaged ones, and a changed weight is a silently different model.
"""

from __future__ import annotations

import functools
import json
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from dozerlab.integrity import DamagedFileError, read_json, sha256_file, sha256_json
from dozerlab.learn.data import TARGET_NAMES, blade_part_of
from dozerlab.learn.models import ForceModel
from dozerlab.runtime import DozerlabError, OutputKind

if TYPE_CHECKING:
    import pandas as pd

INPUT_NAMES = ("velocity", "density", "blade_velocity")


def model_dir_kind(what: str, name: str, evolution: bool) -> OutputKind:
    """The kind of a model directory that command ``name`` writes: an MLflow model directory
    holding this package's ``artifacts/meta.json`` and weights, of an evolution model (its
    metadata has a ``horizon``) or not, as ``evolution`` says, so that ``train`` never replaces
    an evolution model nor ``train-dynamics`` a force model."""

    def recognise(path: Path) -> bool:
        art = path / "artifacts"
        if path.is_symlink() or not (path / "MLmodel").is_file():
            return False
        meta = json.loads((art / "meta.json").read_text())
        return (
            (art / "weights.pt").is_file() and "kind" in meta and ("horizon" in meta) == evolution
        )

    return OutputKind(what, recognise, name)


#: What ``dozerlab train`` writes; an earlier force model of ours at ``--out`` may be replaced.
MODEL_DIR = model_dir_kind("a dozerlab force model directory (written by train)", "train", False)


def build(meta: dict[str, Any], weights: str | Path) -> ForceModel:
    """Rebuild a :class:`ForceModel` from its metadata and state-dict file (CPU, eval mode)."""
    # models saved before the contact inputs have no "contact" key, before the volume's bins
    # around the blade part no "blade_part" (they read the whole grid)
    part = meta.get("blade_part")
    model = ForceModel(
        meta["kind"],
        tuple(meta["grid"]),
        meta["history"],
        bool(meta.get("contact", False)),
        None if part is None else blade_part_of(part),
    )
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


def require_inputs(arrays: Any) -> None:
    """Refuse model input that is not a dict holding every one of :data:`INPUT_NAMES` (both
    model families take these), naming what is wrong."""
    if not isinstance(arrays, dict):
        raise DozerlabError(
            f"model input must be a dict with keys {list(INPUT_NAMES)}, got {type(arrays).__name__}"
        )
    missing = [k for k in INPUT_NAMES if k not in arrays]
    if missing:
        raise DozerlabError(f"model input lacks {missing}; it needs {list(INPUT_NAMES)}")


def check_inputs(arrays: Any, grid: tuple[int, int, int]) -> dict[str, np.ndarray]:
    """The three input arrays, shape-checked against the model's grid."""
    require_inputs(arrays)
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


def model_extras(model: ForceModel, example: dict[str, np.ndarray]) -> dict[str, Any]:
    """A force model's own arguments of ``mlflow.pyfunc.save_model``: its
    signature and input example (the first row of per-row store arrays)."""
    return {
        "signature": signature(model.grid),
        "input_example": {
            k: np.ascontiguousarray(example[k][:1], dtype=np.float32) for k in INPUT_NAMES
        },
    }


def write_artifacts(model: Any, meta: dict[str, Any], workdir: Path) -> dict[str, str]:
    """``weights.pt`` (the state dict) and ``meta.json`` (``meta`` and ``model.spec()``) in
    ``workdir``: a model directory's MLflow artifacts."""
    weights, meta_path = workdir / "weights.pt", workdir / "meta.json"
    torch.save({k: v.detach().cpu() for k, v in model.state_dict().items()}, weights)
    meta_path.write_text(json.dumps({**meta, **model.spec()}, indent=1))
    return {"weights": str(weights), "meta": str(meta_path)}


#: ``meta.json``'s record of the SHA-256 of every other file of the directory, by relative path.
FILES_KEY = "files_sha256"
#: ``meta.json``'s record of the SHA-256 of its own content (canonical JSON without this key).
META_KEY = "meta_sha256"


def seal(path: str | Path) -> None:
    """Record the SHA-256 of every file of the saved model directory ``path``, and of the
    metadata itself, in its ``artifacts/meta.json`` (what :func:`verify_model_dir` checks)."""
    path = Path(path)
    meta_file = path / "artifacts" / "meta.json"
    meta = json.loads(meta_file.read_text())
    files = sorted(f for f in path.rglob("*") if f.is_file() and f != meta_file)
    meta[FILES_KEY] = {f.relative_to(path).as_posix(): sha256_file(f) for f in files}
    meta[META_KEY] = sha256_json(meta)
    meta_file.write_text(json.dumps(meta, indent=1))


def verify_model_dir(path: str | Path, what: str = "dozerlab model") -> dict[str, Any]:
    """Check every file of a saved model directory against the digests in its ``meta.json``;
    return the metadata.

    Raises :class:`FileNotFoundError` for a directory without ``artifacts/meta.json`` and
    ``weights.pt``, and :class:`~dozerlab.integrity.DamagedFileError` naming the file when
    ``meta.json`` is not JSON or differs from its recorded digest, when a recorded file is
    missing or its bytes differ, or when the directory has no digests (saved before them).
    """
    path = Path(path)
    art = path / "artifacts"
    if not (art / "meta.json").is_file() or not (art / "weights.pt").is_file():
        raise FileNotFoundError(
            f"not a {what} directory (no artifacts/meta.json, weights.pt): {path}"
        )
    remedy = f"re-run the `train` that wrote it, or copy {path} again"
    meta = read_json(art / "meta.json", f"a {what}'s metadata")
    if not isinstance(meta, dict) or not isinstance(meta.get(FILES_KEY), dict):
        raise DamagedFileError(
            f"{art / 'meta.json'} records no SHA-256 of the model's files (saved by a dozerlab "
            f"older than them, or not a {what}'s), so they cannot be verified; {remedy}"
        )
    if meta.get(META_KEY) != sha256_json({k: v for k, v in meta.items() if k != META_KEY}):
        raise DamagedFileError(
            f"{art / 'meta.json'} is damaged: its content differs from the SHA-256 recorded at "
            f"saving; {remedy}"
        )
    for name, digest in meta[FILES_KEY].items():
        file = path / name
        if not file.is_file():
            raise DamagedFileError(f"{file} is missing (recorded in meta.json); {remedy}")
        if sha256_file(file) != digest:
            raise DamagedFileError(
                f"{file} is damaged: its bytes differ from the SHA-256 recorded at saving (cut "
                f"short or changed); {remedy}"
            )
    if "artifacts/weights.pt" not in meta[FILES_KEY]:
        raise DamagedFileError(f"{art / 'meta.json'} records no digest of weights.pt; {remedy}")
    return meta


def read_artifacts(path: str | Path, what: str = "dozerlab model") -> tuple[dict[str, Any], Path]:
    """The metadata and weights file of a saved model directory, every file checked
    (:func:`verify_model_dir`)."""
    return verify_model_dir(path, what), Path(path) / "artifacts" / "weights.pt"


@dataclass(frozen=True)
class PyfuncFormat:
    """How one family of models is written as an MLflow pyfunc directory and read back.

    ``what`` names the directory in messages; ``entry`` is the family's models-from-code file
    (loading runs it instead of unpickling an object); ``build(meta, weights)`` rebuilds a model;
    ``extras(model, arrays)`` gives the family's own ``save_model`` arguments
    (signature, input example from per-row store arrays, metadata); ``class_name`` and
    ``predict(model, model_input)`` make the family's MLflow ``PythonModel`` class
    (:func:`python_model_class`), which the entry sets; ``check(meta, path)`` refuses a directory
    of another family before it is built.
    """

    what: str
    entry: Path
    build: Callable[[dict[str, Any], str | Path], Any]
    extras: Callable[[Any, dict[str, np.ndarray]], dict[str, Any]]
    class_name: str
    predict: Callable[[Any, Any], Any]
    check: Callable[[dict[str, Any], str | Path], None] = lambda meta, path: None

    def kwargs(
        self, model: Any, meta: dict[str, Any], workdir: Path, arrays: dict[str, np.ndarray]
    ) -> dict[str, Any]:
        """The arguments of ``mlflow.pyfunc.save_model`` (files go to ``workdir``); the run logs
        the saved directory (``JobRun.log_model``)."""
        return {
            "python_model": str(self.entry),
            "artifacts": write_artifacts(model, meta, workdir),
            "pip_requirements": pip_requirements(),
            **self.extras(model, arrays),
        }

    def save(
        self, model: Any, meta: dict[str, Any], path: str | Path, arrays: dict[str, np.ndarray]
    ) -> None:
        """Save ``model`` as an MLflow pyfunc directory at ``path`` (which must not exist);
        ``arrays`` are per-row store arrays for the input example."""
        import mlflow.pyfunc

        with tempfile.TemporaryDirectory() as tmp:
            mlflow.pyfunc.save_model(path=str(path), **self.kwargs(model, meta, Path(tmp), arrays))
        seal(path)

    def load(self, path: str | Path) -> tuple[Any, dict[str, Any]]:
        """Load a saved model directory directly (no MLflow runtime): the model and its
        metadata."""
        meta, weights = read_artifacts(path, self.what)
        self.check(meta, path)
        return self.build(meta, weights), meta


def predict_frame(model: ForceModel, arrays: dict[str, np.ndarray]) -> pd.DataFrame:
    """(B, 6) DataFrame force_x … torque_z (N, N·m) of per-step input arrays (the contract)."""
    import pandas as pd  # only MLflow's predict path needs it; the reduced loop does not

    return pd.DataFrame(predict_arrays(model, arrays), columns=list(TARGET_NAMES))


#: The force models' pyfunc directories.
FORMAT = PyfuncFormat(
    "dozerlab model",
    Path(__file__).with_name("pyfunc_entry.py"),
    build,
    model_extras,
    "ForcePyfunc",
    predict_frame,
)
save, load = FORMAT.save, FORMAT.load


@functools.cache
def python_model_class(fmt: PyfuncFormat) -> type:
    """``fmt``'s MLflow ``PythonModel`` class, made on first use: making it imports MLflow, which
    the jobs that read model directories directly (:meth:`PyfuncFormat.load`) never need."""
    from dozerlab.learn.pyfunc_model import model_class

    return model_class(fmt.class_name, fmt.what, fmt.build, fmt.predict)


def __getattr__(name: str) -> Any:
    # ``ForcePyfunc``: what pyfunc_entry.py sets, made when MLflow's loader runs it.
    if name == FORMAT.class_name:
        return python_model_class(FORMAT)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
