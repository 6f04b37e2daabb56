import mlflow
import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.learn.dynamics import pyfunc
from dozerlab.learn.dynamics.train import train_dynamics
from dozerlab.runtime import DozerlabError

from .helpers import translating


@pytest.mark.parametrize("variant", ["persistence", "ridge", "unet", "ridge-momentum"])
def test_saved_model_reloads_and_predicts_the_same_numbers(variant, tmp_path):
    kind, momentum = variant.removesuffix("-momentum"), variant.endswith("-momentum")
    cfg = load_config(
        {
            "mlflow": {"enabled": False},
            "learn": {"validation_block": 5},
            "dynamics": {
                "epochs": 1,
                "samples_per_epoch": 8,
                "history": 3,
                "horizon": 2,
                "ridge_horizon": 2,  # every kind predicts the rows the inputs below hold
                "ridge_y_bands": [2],  # the helpers' grid: 5 columns, 4 rows
                "ridge_z_bands": [1],
                "ridge_momentum": momentum,
            },
        }
    )
    stores = [translating(i, rows=30) for i in range(2)]
    model = train_dynamics(kind, stores, cfg, progress=False).model
    arrays = {
        "velocity": stores[0].velocity,
        "density": stores[0].density,
        "blade_velocity": stores[0].blade_velocity,
    }
    pyfunc.save(model, {"train_points": []}, tmp_path / variant, arrays)
    held = translating(7, rows=30)
    rows = np.arange(4)[:, None] + np.arange(5)[None, :]
    inputs = {
        "velocity": held.velocity[rows[:, :3]],
        "density": held.density[rows[:, :3]],
        "blade_velocity": held.blade_velocity[rows],
    }
    expected = pyfunc.predict_arrays(model, inputs)
    loaded = mlflow.pyfunc.load_model(str(tmp_path / variant))
    assert loaded.metadata.metadata["history"] == 3 and loaded.metadata.metadata["horizon"] == 2
    got = loaded.predict(inputs)
    assert got["velocity"].shape == (4, 2, *held.grid, 3) and got["density"].shape == (
        4,
        2,
        *held.grid,
    )
    for name in ("velocity", "density"):
        np.testing.assert_allclose(got[name], expected[name], rtol=1e-5, atol=1e-4)
    direct, meta = pyfunc.load(tmp_path / variant)
    np.testing.assert_array_equal(
        pyfunc.predict_arrays(direct, inputs)["density"], expected["density"]
    )
    assert meta["kind"] == kind
    assert direct.momentum == meta["momentum"] == (kind == "ridge" and momentum)


def test_missing_array_and_force_model_directory_are_refused(tmp_path):
    from dozerlab.learn.dynamics.models import DynamicsModel
    from dozerlab.learn.pyfunc import seal

    model = DynamicsModel("persistence", (4, 3, 2), 1, 1, 0.01, (0.1, 0.1, 0.1))
    with pytest.raises(DozerlabError, match=r"lacks \['blade_velocity'\]"):
        pyfunc.predict_arrays(
            model, {"velocity": np.zeros((1, 1, 4, 3, 2, 3)), "density": np.zeros((1, 1, 4, 3, 2))}
        )
    (tmp_path / "artifacts").mkdir()
    (tmp_path / "artifacts" / "meta.json").write_text(
        '{"kind": "unet", "grid": [4, 3, 2], "history": 3}'
    )
    (tmp_path / "artifacts" / "weights.pt").write_bytes(b"")
    seal(tmp_path)  # its files whole: what is refused is the family
    with pytest.raises(DozerlabError, match="force model"):
        pyfunc.load(tmp_path)
