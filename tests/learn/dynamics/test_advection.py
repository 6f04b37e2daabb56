import numpy as np
import torch

from dozerlab.learn.dynamics.advection import advect, frame_shift

from .helpers import BIN, DT, translating


def test_frame_shift_is_blade_velocity_times_interval_over_bin():
    shift = frame_shift(torch.tensor([[1.0, 0.0, -0.5]]), 0.01, (0.05, 0.1, 0.025))
    np.testing.assert_allclose(shift.numpy(), [[0.2, 0.0, -0.2]])


def test_material_translating_one_bin_per_row_is_carried_exactly():
    s = translating(0, decay=1.0)
    rho, v = advect(
        torch.from_numpy(s.density[:1]),
        torch.from_numpy(s.velocity[:1]),
        torch.from_numpy(s.blade_velocity[1:2]),
        DT,
        BIN,
    )
    # all but the front bins, where material enters from outside the volume
    np.testing.assert_allclose(rho[0, :-1].numpy(), s.density[1, :-1], rtol=1e-5, atol=1e-2)
    np.testing.assert_allclose(v[0, :-1].numpy(), s.velocity[1, :-1], rtol=1e-5, atol=1e-5)


def test_mass_is_conserved_when_nothing_crosses_the_volume_faces():
    gen = torch.Generator().manual_seed(0)
    rho = torch.zeros(2, 8, 7, 6)
    rho[:, 2:-2, 2:-2, 2:-2] = 1000 * torch.rand(2, 4, 3, 2, generator=gen)
    v = torch.randn(2, 8, 7, 6, 3, generator=gen) * (rho > 0).unsqueeze(-1)
    vb = torch.tensor([[1.0, 0.0, 0.0], [0.5, 0.2, 0.0]])
    new, _ = advect(rho, v, vb, 0.01, (0.05, 0.05, 0.05))
    assert (new >= 0).all()
    np.testing.assert_allclose(new.sum((1, 2, 3)).numpy(), rho.sum((1, 2, 3)).numpy(), rtol=1e-5)
