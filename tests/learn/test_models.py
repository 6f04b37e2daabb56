import numpy as np
import pytest
import torch
from torch.nn import functional as F

from dozerlab.learn.metrics import component_metrics
from dozerlab.learn.models import (
    Conv3d,
    ForceModel,
    n_channels,
    pushing_gate,
    resize_trilinear,
)
from dozerlab.learn.pyfunc import predict_arrays
from dozerlab.learn.train import TrainingDiverged, train_model
from dozerlab.learn.validate import predict_store
from tests.helpers import in_memory


@pytest.mark.parametrize(
    "kind",
    [
        "linear",
        "mlp",
        pytest.param("cnn", marks=pytest.mark.slow),  # 20 epochs of 3-D convolutions
        pytest.param("unet", marks=pytest.mark.slow),
    ],
)
def test_models_learn_a_known_force(kind, train_stores, config):
    torch.set_num_threads(1)
    result = train_model(kind, train_stores, config, progress=False)
    assert np.isfinite(result.val_loss).all()
    held_out = in_memory(1.0, 0.1, seed=99)  # a new point inside the training ranges
    _, pred, true = predict_store(result.model, held_out)
    m = component_metrics(pred, true)
    for comp in ("force_x", "force_z", "torque_y"):
        assert m[comp]["rel_rmse"] < 0.1 and m[comp]["r2"] > 0.9, (comp, m[comp])


def test_untrained_model_is_far_off(train_stores):
    # The tolerance above is meaningful: an unfitted model with identity normalisation misses.
    model = ForceModel("mlp", train_stores[0].grid).eval()
    s = train_stores[0]
    pred = predict_arrays(
        model, {"velocity": s.velocity, "density": s.density, "blade_velocity": s.blade_velocity}
    )
    assert component_metrics(pred, s.target)["force_x"]["rel_rmse"] > 0.5


def test_history_model_trains(train_stores, config):
    config["learn"].update(history=3, epochs=2)
    result = train_model("cnn", train_stores[:2], config, progress=False)
    assert result.model.history == 3 and np.isfinite(result.val_loss).all()


@pytest.mark.parametrize("kind", ["linear", "mlp"])
def test_nan_guard_trips_on_poisoned_input(kind, train_stores, config):
    poisoned = in_memory(1.0, 0.1, seed=5)
    poisoned.velocity[3, 0, 0, 0, 0] = np.nan
    with pytest.raises(TrainingDiverged, match="diverged"):
        train_model(kind, [poisoned, *train_stores[:2]], config, progress=False)


def test_seeded_training_is_reproducible(train_stores, config):
    config["learn"]["epochs"] = 2
    a = train_model("mlp", train_stores[:2], config, progress=False)
    b = train_model("mlp", train_stores[:2], config, progress=False)
    assert a.val_loss == b.val_loss


def test_linear_model_is_mirror_equivariant(train_stores, config):
    from dozerlab.learn.train import mirror_y

    config["learn"]["history"] = 2
    model = train_model("linear", train_stores, config, progress=False).model
    s = train_stores[0]
    rows = np.arange(1, 21)[:, None] + np.arange(-1, 1)[None, :]
    v, rho, vb = (
        torch.from_numpy(a[rows]).clone() for a in (s.velocity, s.density, s.blade_velocity)
    )
    rho = (
        rho * torch.linspace(0.5, 1.5, rho.shape[3])[:, None]
    )  # a lopsided pile: odd features are not zero
    y = torch.zeros(v.shape[0], 6)
    with torch.no_grad():
        pred = model(v, rho, vb)
        mirror_y(v, rho, vb, y, torch.ones(v.shape[0], dtype=torch.bool))
        mirrored = model(v, rho, vb)
    assert pred[:, 1].abs().max() > 0  # the odd targets see the imbalance
    parity = torch.tensor([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
    torch.testing.assert_close(
        mirrored, pred * parity, rtol=1e-4, atol=1e-3 * float(pred.abs().max())
    )


@pytest.mark.parametrize(
    ("shape", "size"), [((2, 3, 4, 3, 2), (8, 6, 4)), ((1, 2, 5, 3, 1), (9, 7, 2))]
)
def test_resize_trilinear_is_torchs_interpolation(shape, size):
    """The matrix form equals F.interpolate's trilinear resize, values and gradients."""
    x = torch.randn(*shape, dtype=torch.float64, requires_grad=True)
    ref = F.interpolate(x, size=size, mode="trilinear", align_corners=False)
    out = resize_trilinear(x, size)
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)
    g = torch.randn_like(ref)
    (grad_ref,) = torch.autograd.grad(ref, x, g)
    (grad,) = torch.autograd.grad(out, x, g)
    torch.testing.assert_close(grad, grad_ref, rtol=0, atol=1e-12)


def test_resize_matrix_made_in_inference_mode_serves_training():
    """A model first called for inference can still be trained in the same process."""
    x = torch.randn(1, 1, 3, 5, 7)
    with torch.inference_mode():
        resize_trilinear(x, (6, 10, 13))
    w = torch.ones((), requires_grad=True)
    resize_trilinear(x * w, (6, 10, 13)).sum().backward()
    assert w.grad is not None


@pytest.mark.parametrize(
    ("cin", "k", "stride", "grid"), [(8, 3, 1, (16, 12, 8)), (24, 2, 1, (17, 13, 9))]
)
def test_conv3d_inference_is_torchs_convolution(cin, k, stride, grid):
    """Inference takes oneDNN for a large convolution and agrees with nn.Conv3d; training takes
    torch's own path, gradients included; the state dict is nn.Conv3d's."""
    torch.manual_seed(0)
    conv = Conv3d(cin, 8, k, stride=stride, padding=(k - 1) // 2)
    ref = torch.nn.Conv3d(cin, 8, k, stride=stride, padding=(k - 1) // 2)
    ref.load_state_dict(conv.state_dict())
    x = torch.randn(1, cin, *grid)
    with torch.inference_mode():
        assert conv.uses_onednn(x)
        torch.testing.assert_close(conv(x), ref(x), rtol=1e-5, atol=1e-5)
    xg = x.clone().requires_grad_(True)
    assert not conv.uses_onednn(xg)
    out = conv(xg)
    torch.testing.assert_close(out, ref(x), rtol=0, atol=0)
    out.sum().backward()
    assert conv.weight.grad is not None and xg.grad is not None
    small = torch.randn(1, cin, 4, 3, 2)
    with torch.inference_mode():
        assert not conv.uses_onednn(small)  # the weight reordering would cost more


@pytest.mark.parametrize("history", [1, 3])
def test_raw_features_are_the_documented_channels(history):
    """Per step: v − v_b, ρ, ρ(v − v_b), ρv; then Δρ and Δ(ρv) of each step but the oldest."""
    gen = torch.Generator().manual_seed(0)
    b, grid = 2, (4, 3, 2)
    v = torch.randn(b, history, *grid, 3, generator=gen)
    rho = torch.rand(b, history, *grid, generator=gen)
    vb = torch.randn(b, history, 3, generator=gen)
    x, c = ForceModel("linear", grid, history).raw_features(v, rho, vb)
    assert x.shape == (b, n_channels(history), *grid)
    torch.testing.assert_close(c, vb.reshape(b, -1), rtol=0, atol=0)
    for h in range(history):
        rel = v[:, h] - vb[:, h, None, None, None, :]
        want = [*rel.unbind(-1), rho[:, h], *(rho[:, h, ..., None] * rel).unbind(-1)]
        want += [*(rho[:, h, ..., None] * v[:, h]).unbind(-1)]
        for k, channel in enumerate(want):
            torch.testing.assert_close(x[:, 10 * h + k], channel, rtol=0, atol=0)
    for h in range(1, history):
        base = 10 * history + 4 * (h - 1)
        torch.testing.assert_close(x[:, base], rho[:, h] - rho[:, h - 1], rtol=0, atol=0)
        mom = rho[:, h, ..., None] * v[:, h] - rho[:, h - 1, ..., None] * v[:, h - 1]
        for a in range(3):
            torch.testing.assert_close(x[:, base + 1 + a], mom[..., a], rtol=0, atol=0)


def test_pushing_gate_is_the_horizontal_share_times_the_density_at_the_face():
    rho = torch.zeros(3, 2, 4, 3, 2)
    rho[:, -1, 0] = 1200.0  # the face bins at the newest step
    rho[:, -1, 1:] = 500.0  # further ahead: not the face
    vb = torch.zeros(3, 2, 3)
    vb[0, -1] = torch.tensor([1.0, 0.0, 0.0])  # pushing straight ahead
    vb[1, -1] = torch.tensor([0.0, 0.0, 1.0])  # lifted straight up
    vb[2, -1] = torch.tensor([0.6, 0.0, -0.8])  # down a slope
    torch.testing.assert_close(pushing_gate(rho, vb), torch.tensor([1200.0, 0.0, 720.0]))
    assert pushing_gate(rho, torch.zeros(3, 2, 3)).eq(0).all()  # at rest


def test_contact_model_never_pulls_the_blade(train_stores):
    s = train_stores[0]
    arrays = {"velocity": s.velocity, "density": s.density, "blade_velocity": s.blade_velocity}
    for contact in (True, False):
        model = ForceModel("mlp", s.grid, contact=contact).eval()
        model.y_mean[0] = 1e6  # an untrained model that would predict a pull
        assert model.spec()["contact"] is contact
        pulls = predict_arrays(model, arrays)[:, 0] > 0
        assert pulls.all() if not contact else not pulls.any()


def test_linear_contact_weights_follow_the_gate(train_stores, config):
    """A blade lifted straight up with the same fields pushes nothing: with the contact inputs
    the linear model learns it, without them its one set of weights cannot."""
    lifted = []
    for s in train_stores:
        up = in_memory(float(s.point["speed"]), float(s.point["depth"]), steps=60, seed=7)
        up.blade_velocity[:, :] = [0.0, 0.0, float(s.point["speed"])]
        up.target[:, :] = 0.0
        up.point = {**up.point, "scenario": "lifted"}
        lifted.append(up)
    errors = {}
    for contact in (True, False):
        config["learn"]["contact"] = contact
        model = train_model("linear", [*train_stores, *lifted], config, progress=False).model
        _, pred, true = predict_store(model, in_memory(1.0, 0.1, seed=99))
        _, pred_up, _ = predict_store(model, lifted[0])
        errors[contact] = (
            component_metrics(pred, true)["force_x"]["rel_rmse"],
            float(np.abs(pred_up[:, 0]).max() / np.abs(true[:, 0]).mean()),
        )
    assert errors[True][0] < 0.1 and errors[True][1] < 0.05, errors
    assert errors[False][1] > 2 * errors[True][1], errors


@pytest.mark.parametrize("kind", ["linear", "mlp", "cnn", "unet"])
def test_a_model_with_a_blade_part_reads_only_those_bins(kind):
    """Beside and above the blade part the fields do not reach the model: the backbone is
    built on the part's grid, and changing the other bins changes nothing."""
    torch.manual_seed(0)
    model = ForceModel(kind, (8, 10, 6), history=2, contact=True, blade_part=(3, 2, 8, 4)).eval()
    assert model.spec()["blade_part"] == [3, 2, 8, 4]
    v, rho = torch.randn(3, 2, 8, 10, 6, 3), torch.rand(3, 2, 8, 10, 6) * 1000
    vb = torch.randn(3, 2, 3)
    with torch.no_grad():
        before = model(v, rho, vb)
        v[:, :, :, :2], rho[:, :, :, 8:], v[..., 4:, :] = 5.0, 3000.0, -2.0
        rho[:, :, :3] = 2500.0  # behind the face
        after = model(v, rho, vb)
        rho[:, :, 3, 4, 1] += 500.0  # a bin of the part, against the face
        moved = model(v, rho, vb)
    torch.testing.assert_close(before, after)
    assert not torch.allclose(after, moved)
    with pytest.raises(ValueError, match="blade_part"):
        ForceModel(kind, (8, 10, 6), blade_part=(0, 2, 11, 4))
