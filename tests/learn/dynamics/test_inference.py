import copy
import math

import numpy as np
import pytest
import torch

from dozerlab.learn.dynamics.advection import advect
from dozerlab.learn.dynamics.inference import RidgeInference, advect_row
from dozerlab.learn.dynamics.models import DynamicsModel

from .helpers import BIN, DT, GRID


def _fields(gen, rows, grid=GRID):
    """Fields with empty bins (density 0) and moving material, and a blade velocity with a
    vertical part, as the loop reads them."""
    rho = 1800.0 * torch.rand(rows, *grid, generator=gen)
    rho[rho < 400.0] = 0.0
    v = 0.5 * torch.randn(rows, *grid, 3, generator=gen) * (rho > 0).unsqueeze(-1)
    return v, rho


def _ridge(history, horizon, y_bands=(), z_bands=(), momentum=False):
    """A ridge with random weights and normalisation, clamps that bind on some bins."""
    torch.manual_seed(history + 10 * horizon + len(y_bands) + len(z_bands))
    model = DynamicsModel(
        "ridge",
        GRID,
        history,
        horizon,
        DT,
        BIN,
        y_bands=y_bands,
        z_bands=z_bands,
        momentum=momentum,
    )
    with torch.no_grad():
        model.net.weight.normal_(std=0.05)
        model.net.bias.normal_(std=0.1)
        model.chan_mean.normal_()
        model.chan_std.uniform_(0.5, 2.0)
        model.cond_mean.normal_()
        model.cond_std.uniform_(0.5, 2.0)
        model.res_std.copy_(torch.tensor([100.0, 0.05, 0.04, 0.06]))
        model.v_lo.fill_(-0.8)
        model.v_hi.fill_(0.9)
        model.rho_hi.fill_(1850.0)
    return model.eval()


def test_one_advected_row_is_the_modules():
    gen = torch.Generator().manual_seed(3)
    v, rho = _fields(gen, 1)
    vb = torch.tensor([[0.9, 0.1, -0.3]])
    want_rho, want_v = advect(rho, v, vb, DT, BIN)
    scale = np.array([DT / b for b in BIN], np.float32)
    got_rho, got_v = advect_row(rho[0].numpy(), v[0].numpy(), vb[0].numpy() * scale, scale)
    np.testing.assert_allclose(got_rho, want_rho[0].numpy(), rtol=1e-5, atol=1e-2)
    np.testing.assert_allclose(got_v, want_v[0].numpy(), rtol=1e-5, atol=1e-5)
    # material moved: the comparison is not of two copies of the input
    assert np.abs(got_rho - rho[0].numpy()).max() > 10.0


@pytest.mark.parametrize(
    ("history", "horizon", "y_bands", "z_bands", "momentum"),
    [
        (2, 1, (), (), False),
        (2, 1, (), (1, 2), False),
        (3, 2, (1, 3), (1,), False),
        (2, 3, (), (1, 2), True),
    ],
)
def test_the_ridge_inference_is_the_modules_forward(history, horizon, y_bands, z_bands, momentum):
    model = _ridge(history, horizon, y_bands, z_bands, momentum)
    fast = RidgeInference(model)
    gen = torch.Generator().manual_seed(horizon)
    v, rho = _fields(gen, history)
    # a region without material, as the air over a bed: neighbourhoods with nothing in them
    rho[:, :4], v[:, :4] = 0.0, 0.0
    vb = torch.tensor([[0.9, 0.05 * j, -0.2 + 0.1 * j] for j in range(history + horizon)])
    with torch.no_grad():
        # against the forward in float64: the module's own float32 sums are off by up to
        # 1.2e-5 m/s here, as far as the two float32 paths are from each other
        exact = copy.deepcopy(model).double()
        want_v, want_rho = exact(v[None].double(), rho[None].double(), vb[None].double())
    got_v, got_rho = fast.predict(v.numpy(), rho.numpy(), vb.numpy())
    assert got_v.shape == (horizon, *GRID, 3) and got_rho.shape == (horizon, *GRID)
    np.testing.assert_allclose(got_rho, want_rho[0].numpy(), rtol=1e-5, atol=0.05)
    np.testing.assert_allclose(got_v, want_v[0].numpy(), rtol=1e-5, atol=1e-5)
    # the correction and the clamps are exercised, not only the advected rows
    _, base_rho = model.base(v[None], rho[None], vb[None])
    assert np.abs(got_rho - base_rho[0].numpy()).max() > 1.0
    assert math.isclose(float(got_v.max()), 0.9, rel_tol=1e-6)


def test_only_a_ridge_has_this_inference():
    with pytest.raises(ValueError, match="needs a ridge model, got 'unet'"):
        RidgeInference(DynamicsModel("unet", GRID, 2, 1, DT, BIN))
