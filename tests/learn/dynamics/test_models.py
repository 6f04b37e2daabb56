import numpy as np
import pytest
import torch

from dozerlab.config import load_config
from dozerlab.learn.dynamics.metrics import rollout
from dozerlab.learn.dynamics.models import DynamicsModel
from dozerlab.learn.dynamics.train import train_dynamics
from dozerlab.runtime import DozerlabError

from .helpers import BIN, DT, GRID, translating


def config(**dynamics):
    return load_config(
        {
            "mlflow": {"enabled": False},
            "learn": {"validation_block": 5},
            # the rule holds away from the front face, where unknown material enters; long
            # validation rollouts (which pick alpha, stop the U-Net) would mostly weigh that inflow
            "dynamics": {
                "epochs": 6,
                "samples_per_epoch": 64,
                "learning_rate": 3e-3,
                "ridge_alphas": [1e-3],
                "val_rollout": 2,
                "ridge_z_bands": [1, 2],  # the helpers' grid has 4 rows
                **dynamics,
            },
        }
    )


@pytest.fixture(scope="module")
def rule_stores():
    return [translating(i) for i in range(4)], translating(9)


def _rollout_error(model, store, steps):
    """Relative L2 of density and mass-weighted velocity after ``steps`` rows, away from the
    front bins where unknown material enters."""
    r = rollout(model, store, steps, 3)
    pred, true = r["fields"]
    keep = slice(0, GRID[0] - steps - 1)
    rho_err = np.linalg.norm(pred[:, -1, keep] - true[:, -1, keep]) / np.linalg.norm(
        true[:, -1, keep]
    )
    return rho_err, r


@pytest.mark.parametrize(
    ("kind", "tol", "gain", "epochs", "momentum"),
    [
        ("ridge", 0.01, 5, 1, False),
        ("ridge", 0.01, 5, 1, True),
        pytest.param("unet", 0.08, 2, 12, False, marks=pytest.mark.slow),  # 12 U-Net epochs
    ],
)
def test_model_learns_translation_with_decay_and_rolls_it_out(
    kind, tol, gain, epochs, momentum, rule_stores
):
    train, held = rule_stores
    torch.manual_seed(0)
    cfg = config(epochs=epochs, ridge_momentum=momentum)
    result = train_dynamics(kind, train, cfg, progress=False)
    model = result.model
    assert model.momentum == momentum
    persistence = DynamicsModel("persistence", GRID, 2, 1, DT, BIN)
    err, _ = _rollout_error(model, held, 4)
    base, _ = _rollout_error(persistence, held, 4)
    assert err < tol, (kind, err)
    assert base > 0.3
    # the decay is learned, not in the advection the models start from
    advection_only = DynamicsModel(
        kind,
        GRID,
        2,
        model.horizon,
        DT,
        BIN,
        y_bands=model.y_bands,
        z_bands=model.z_bands,
        momentum=model.momentum,
    )
    advection_only.load_state_dict({**model.state_dict(), **_zero_net(model)})
    assert _rollout_error(advection_only, held, 4)[0] > gain * err


def _zero_net(model):
    return {k: torch.zeros_like(v) for k, v in model.state_dict().items() if k.startswith("net.")}


def test_persistence_is_exact_on_a_steady_field():
    from .helpers import steady

    s = steady()
    model = DynamicsModel("persistence", GRID, 2, 3, DT, BIN)
    v, rho = model(
        torch.from_numpy(s.velocity[None, :2]),
        torch.from_numpy(s.density[None, :2]),
        torch.from_numpy(s.blade_velocity[None, :5]),
    )
    assert v.shape == (1, 3, *GRID, 3) and rho.shape == (1, 3, *GRID)
    np.testing.assert_array_equal(rho[0].numpy(), s.density[2:5])
    r = rollout(model, s, 15, 2)
    assert (r["sums"][:, [0, 2]] == 0).all() and (r["mass"] == r["mass_true"]).all()


def test_wrong_shapes_are_refused_with_the_expected_ones():
    model = DynamicsModel("ridge", GRID, 2, 1, DT, BIN)
    v, rho, vb = torch.zeros(1, 2, *GRID, 3), torch.zeros(1, 2, *GRID), torch.zeros(1, 3, 3)
    with pytest.raises(
        DozerlabError, match=r"'blade_velocity' has shape \(1, 2, 3\), expected \(1, 3, 3\)"
    ):
        model(v, rho, vb[:, :2])
    with pytest.raises(DozerlabError, match="history = 2"):
        model(v[:, :1], rho[:, :1], vb)


@pytest.mark.parametrize("bands", [((), ()), ((1, 3), (1,))])
def test_the_ridge_stencil_is_its_design_rows_times_its_weights(bands):
    # forward sums by parts what the closed-form fit's design rows (feature c·27 + 9i + 3j + k,
    # edges replicated) times each box's weights give: a model fitted on design rows predicts
    # with them
    model = DynamicsModel("ridge", GRID, 2, 1, DT, BIN, y_bands=bands[0], z_bands=bands[1])
    net = model.net
    torch.manual_seed(0)
    with torch.no_grad():
        net.weight.normal_()
        net.bias.normal_()
        x = torch.randn(2, net.weight.shape[2] // 27, *GRID)
        c = torch.randn(2, 9)
        rows = net.design(x, model.coords, c)
        b, nx, ny, nz = x.shape[0], *GRID
        pad = torch.nn.functional.pad(x, (1, 1, 1, 1, 1, 1), mode="replicate")
        i, j, k, ch = 2, 1, 0, 3  # one stencil feature, read off the padded grid directly
        np.testing.assert_array_equal(
            rows[..., ch * 27 + 9 * i + 3 * j + k].numpy(),
            pad[:, ch, i : i + nx, j : j + ny, k : k + nz].reshape(b, nx, ny * nz).numpy(),
        )
        want = torch.zeros(b, nx, ny * nz, net.weight.shape[-1])
        for k, idx in enumerate(net.box_rows(GRID)):
            want[:, :, idx] = torch.einsum("bxnd,xdo->bxno", rows[:, :, idx], net.weight[:, k])
            want[:, :, idx] += net.bias[None, :, k, None, :]
        got = net(x, model.coords, c).permute(0, 2, 3, 4, 1).reshape(b, nx, ny * nz, -1)
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-4)


def test_a_ridge_saved_with_one_box_per_layer_loads_as_it_was():
    # models saved before the bands: weight (X, d, outputs), bias (X, outputs)
    torch.manual_seed(1)
    model = DynamicsModel("ridge", GRID, 2, 1, DT, BIN)
    with torch.no_grad():
        model.net.weight.normal_()
        model.net.bias.normal_()
    state = model.state_dict()
    state["net.weight"], state["net.bias"] = state["net.weight"][:, 0], state["net.bias"][:, 0]
    again = DynamicsModel("ridge", GRID, 2, 1, DT, BIN)
    again.load_state_dict(state)
    torch.testing.assert_close(again.net.weight, model.net.weight)
    torch.testing.assert_close(again.net.bias, model.net.bias)


def test_ridge_band_edges_outside_the_grid_are_refused():
    with pytest.raises(ValueError, match=r"y band edges must increase within 1\.\.4"):
        DynamicsModel("ridge", GRID, 2, 1, DT, BIN, y_bands=(3, 5))
