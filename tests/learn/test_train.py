"""Training helpers: the y-mirror augmentation transforms fields and targets consistently."""

import copy

import torch

from dozerlab.learn.train import mirror_y


def _force_and_torque(
    velocity: torch.Tensor, density: torch.Tensor, y: torch.Tensor
) -> torch.Tensor:
    """A physical stand-in for the blade load: total momentum and its moment about the tip,
    of bins at x = i, y = y[j], z = k. velocity (B, H, X, Y, Z, 3), density (B, H, X, Y, Z)."""
    nx, _ny, nz = density.shape[2:]
    pos = torch.stack(
        torch.meshgrid(torch.arange(nx) * 1.0, y, torch.arange(nz) * 1.0, indexing="ij"), dim=-1
    )
    mom = density[:, -1, ..., None] * velocity[:, -1]
    force = mom.sum(dim=(1, 2, 3))
    torque = torch.linalg.cross(pos.expand_as(mom), mom, dim=-1).sum(dim=(1, 2, 3))
    return torch.cat([force, torque], dim=1)


def test_mirror_maps_a_sample_to_its_reflection():
    gen = torch.Generator().manual_seed(0)
    b, h, grid = 4, 2, (3, 4, 2)
    v = torch.randn(b, h, *grid, 3, generator=gen)
    rho = torch.rand(b, h, *grid, generator=gen)
    vb = torch.randn(b, h, 3, generator=gen)
    y = torch.linspace(-0.3, 0.3, grid[1])  # bin centres symmetric about the tip, as in a store
    target = _force_and_torque(v, rho, y)
    mask = torch.tensor([True, False, True, False])
    v2, rho2, vb2, t2 = v.clone(), rho.clone(), vb.clone(), target.clone()
    mirror_y(v2, rho2, vb2, t2, mask)
    # The mirrored target is exactly the load of the mirrored fields ...
    torch.testing.assert_close(t2, _force_and_torque(v2, rho2, y))
    # ... the unmasked samples are untouched, and mirroring twice restores the original.
    torch.testing.assert_close(v2[~mask], v[~mask])
    torch.testing.assert_close(t2[~mask], target[~mask])
    mirror_y(v2, rho2, vb2, t2, mask)
    for a, b_ in ((v2, v), (rho2, rho), (vb2, vb), (t2, target)):
        torch.testing.assert_close(a, b_)
    assert not torch.allclose(target[mask, 1], torch.zeros(2))  # the check above was not vacuous


def test_mirrored_training_still_learns_the_symmetric_loads(train_stores, config):
    import numpy as np

    from dozerlab.learn.metrics import component_metrics
    from dozerlab.learn.train import train_model
    from dozerlab.learn.validate import predict_store
    from tests.helpers import in_memory

    def symmetric(store):  # the synthetic fill is y-symmetric in law; make the loads so too
        store.target[:, [1, 3, 5]] = 0.0
        return store

    torch.set_num_threads(1)
    config["learn"]["mirror"] = True
    stores = [symmetric(copy.deepcopy(s)) for s in train_stores]
    result = train_model("mlp", stores, config, progress=False)
    _, pred, true = predict_store(result.model, symmetric(in_memory(1.0, 0.1, seed=99)))
    m = component_metrics(pred, true)
    for comp in ("force_x", "force_z", "torque_y"):
        assert m[comp]["rel_rmse"] < 0.1, (comp, m[comp])
    assert np.isfinite(result.val_loss).all()
