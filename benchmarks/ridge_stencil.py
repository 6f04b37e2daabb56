"""The ridge evolution model's inference, side by side: its forward (the stencil as one grouped
2D convolution over (y, z) per box of bands, a group per layer along x) with the default bands
(`dynamics.ridge_z_bands`) and with one box per layer, against the stacked 3×3×3 stencil times
the weights (the forward before the convolution) and the product of the design rows the
closed-form fit reads with the same weights; and the whole banded model's forward (advection,
normalisation, stencil, correction) through the module against :class:`RidgeInference`, the
reduced loop's path.

    python benchmarks/ridge_stencil.py [--bins 24 18 8] [--z-bands 1 3] [--history 2] \
        [--horizon 1] [--momentum] [--threads 1]

Random weights and fields on the grid (the default sweep's 24 × 18 × 8); prints the ms per call
(batch 1, as the reduced loop calls it; best of 5 rounds) of each and the largest difference of
their outputs.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
import torch

from dozerlab.config import load_config
from dozerlab.learn.dynamics.inference import RidgeInference
from dozerlab.learn.dynamics.models import (
    FIELD_CHANNELS,
    DynamicsModel,
    RidgeStencil,
    coordinates,
)
from dozerlab.runtime import set_threads


def best_ms(f: Callable[[], object], repeats: int = 50, rounds: int = 5) -> float:
    """The best over ``rounds`` of the mean ms per call of ``repeats`` calls."""
    f()
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(repeats):
            f()
        best = min(best, 1e3 * (time.perf_counter() - t0) / repeats)
    return best


def by_design(
    net: RidgeStencil, x: torch.Tensor, coords: torch.Tensor, c: torch.Tensor
) -> torch.Tensor:
    """The design rows of each box times its weights: what the closed-form fit reads."""
    grid = tuple(x.shape[2:])
    d = net.design(x, coords, c)  # 1, X, Y·Z, features
    out = torch.zeros(1, grid[0], d.shape[2], net.weight.shape[-1])
    for k, idx in enumerate(net.box_rows(grid)):
        out[:, :, idx] = torch.einsum("bxnd,xdo->bxno", d[:, :, idx], net.weight[:, k])
        out[:, :, idx] += net.bias[None, :, k, None, :]
    return out.reshape(1, *grid, -1).permute(0, 4, 1, 2, 3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bins", type=int, nargs=3, default=[24, 18, 8])
    ap.add_argument(
        "--z-bands", type=int, nargs="*", default=load_config({})["dynamics"]["ridge_z_bands"]
    )
    ap.add_argument("--history", type=int, default=2)
    ap.add_argument("--horizon", type=int, default=1)
    ap.add_argument(
        "--momentum",
        action="store_true",
        help="the whole model with the momentum channels (dynamics.ridge_momentum)",
    )
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    set_threads(args.threads)
    torch.manual_seed(0)
    rows = args.history + args.horizon
    channels, cond, outputs = FIELD_CHANNELS * rows, 3 * rows, FIELD_CHANNELS * args.horizon
    grid = (args.bins[0], args.bins[1], args.bins[2])
    one = RidgeStencil(channels, cond, outputs, grid)
    banded = RidgeStencil(channels, cond, outputs, grid, (), tuple(args.z_bands))
    with torch.no_grad():
        for net in (one, banded):
            net.weight.normal_()
            net.bias.normal_()
    x = torch.randn(1, channels, *grid)
    c = torch.randn(1, cond)
    coords = coordinates(grid)

    def by_stencil() -> torch.Tensor:
        """The stacked stencil times one box's weights, the position and control added."""
        n, d = grid[1] * grid[2], 27 * channels
        w, bias = one.weight[:, 0], one.bias[:, 0]
        w_st = w[:, :d].unflatten(1, (channels, 27)).transpose(1, 2).flatten(1, 2)
        out = torch.einsum("bxnd,xdo->bxno", one.stencil(x).flatten(-2), w_st)
        pos = coords.permute(1, 2, 3, 0).reshape(grid[0], n, 3)
        out = out + torch.einsum("xnp,xpo->xno", pos, w[:, d : d + 3])[None]
        out = out + torch.einsum("bc,xco->bxo", c, w[:, d + 3 :])[:, :, None, :]
        out = out + bias[None, :, None, :]
        return out.reshape(1, *grid, -1).permute(0, 4, 1, 2, 3)

    with torch.no_grad():
        ref, ref_b = by_design(one, x, coords, c), by_design(banded, x, coords, c)
        diff = max(
            float((one(x, coords, c) - ref).abs().max()),
            float((by_stencil() - ref).abs().max()),
            float((banded(x, coords, c) - ref_b).abs().max()),
        )
        conv_b = best_ms(lambda: banded(x, coords, c))
        conv = best_ms(lambda: one(x, coords, c))
        stacked = best_ms(by_stencil)
        design = best_ms(lambda: by_design(one, x, coords, c))
    print(
        f"ridge on {grid[0]} x {grid[1]} x {grid[2]} bins, {channels} channels, {outputs} outputs, "
        f"{args.threads} thread(s): forward (grouped convolution) with the z bands "
        f"{args.z_bands} ({len(banded.boxes)} boxes a layer) {conv_b:.2f} ms, with one box "
        f"{conv:.2f} ms; stacked stencil x weights {stacked:.2f} ms ({stacked / conv:.1f}x one "
        f"box's forward); design rows x weights {design:.2f} ms ({design / conv:.1f}x); largest "
        f"difference {diff:.2g} (outputs up to {float(ref.abs().max()):.3g})"
    )

    model_vs_inference(grid, args.history, args.horizon, tuple(args.z_bands), args.momentum)


def model_vs_inference(
    grid: tuple[int, int, int],
    history: int,
    horizon: int,
    z_bands: tuple[int, ...],
    momentum: bool = False,
) -> None:
    """Print the ms per call of a banded ridge model's forward through the module and through
    :class:`RidgeInference` on one window of fields like a bed's (densities 0 or up to
    1800 kg/m³, grains moving at up to ~1 m/s), and their largest difference."""
    model = DynamicsModel(
        "ridge",
        grid,
        history,
        horizon,
        0.01,
        (0.05, 0.05, 0.05),
        z_bands=z_bands,
        momentum=momentum,
    )
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        model.net.weight.normal_(std=0.02, generator=gen)
        model.net.bias.normal_(std=0.1, generator=gen)
        model.chan_std.uniform_(0.5, 2.0, generator=gen)
        model.res_std.copy_(torch.tensor([100.0, 0.05, 0.04, 0.06]))
    model.eval()
    rho = 1800.0 * torch.rand(history, *grid, generator=gen)
    rho[rho < 400.0] = 0.0
    v = 0.5 * torch.randn(history, *grid, 3, generator=gen) * (rho > 0).unsqueeze(-1)
    vb = torch.tensor([[1.0, 0.0, -0.1]] * (history + horizon))
    fast = RidgeInference(model)
    with torch.no_grad():
        ref = model(v[None], rho[None], vb[None])
        module = best_ms(lambda: model(v[None], rho[None], vb[None]))
    arrays = (v.numpy(), rho.numpy(), vb.numpy())
    got = fast.predict(*arrays)
    inference = best_ms(lambda: fast.predict(*arrays))
    dv = float(np.abs(got[0] - ref[0][0].numpy()).max())
    drho = float(np.abs(got[1] - ref[1][0].numpy()).max())
    print(
        f"the whole model (z bands {list(z_bands)}, history {history}, horizon {horizon}, "
        f"momentum {momentum}): "
        f"module forward {module:.2f} ms, RidgeInference {inference:.2f} ms "
        f"({module / inference:.1f}x); largest difference {dv:.2g} m/s, {drho:.2g} kg/m³"
    )


if __name__ == "__main__":
    main()
