"""The ridge evolution model's inference, side by side: its forward (the stencil as one grouped
2D convolution over (y, z), a group per layer along x) against the stacked 3×3×3 stencil times
the weights (the forward before it) and the product of the design rows the closed-form fit
reads with the same weights.

    python benchmarks/ridge_stencil.py [--bins 24 18 8] [--history 2] [--horizon 1] [--threads 1]

Random weights and fields on the grid (the default sweep's 24 × 18 × 8); prints the ms per call
(batch 1, as the reduced loop calls it; best of 5 rounds) of each and the largest difference of
their outputs.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import torch

from dozerlab.learn.dynamics.models import FIELD_CHANNELS, RidgeStencil, coordinates
from dozerlab.runtime import set_threads


def best_ms(f: Callable[[], torch.Tensor], repeats: int = 50, rounds: int = 5) -> float:
    """The best over ``rounds`` of the mean ms per call of ``repeats`` calls."""
    f()
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(repeats):
            f()
        best = min(best, 1e3 * (time.perf_counter() - t0) / repeats)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bins", type=int, nargs=3, default=[24, 18, 8])
    ap.add_argument("--history", type=int, default=2)
    ap.add_argument("--horizon", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    set_threads(args.threads)
    torch.manual_seed(0)
    rows = args.history + args.horizon
    channels, cond, outputs = FIELD_CHANNELS * rows, 3 * rows, FIELD_CHANNELS * args.horizon
    grid = tuple(args.bins)
    net = RidgeStencil(channels, cond, outputs, grid[0])
    with torch.no_grad():
        net.weight.normal_()
        net.bias.normal_()
    x = torch.randn(1, channels, *grid)
    c = torch.randn(1, cond)
    coords = coordinates(grid)  # type: ignore[arg-type]

    def by_design() -> torch.Tensor:
        d = net.design(x, coords, c)  # 1, X, Y·Z, features
        out = torch.einsum("bxnd,xdo->bxno", d, net.weight) + net.bias[None, :, None, :]
        return out.reshape(1, *grid, -1).permute(0, 4, 1, 2, 3)

    def by_stencil() -> torch.Tensor:
        """The stacked stencil times the stencil's weights, the position and control added."""
        n, d = grid[1] * grid[2], 27 * channels
        w = net.weight
        w_st = w[:, :d].unflatten(1, (channels, 27)).transpose(1, 2).flatten(1, 2)
        out = torch.einsum("bxnd,xdo->bxno", net.stencil(x).flatten(-2), w_st)
        pos = coords.permute(1, 2, 3, 0).reshape(grid[0], n, 3)
        out = out + torch.einsum("xnp,xpo->xno", pos, w[:, d : d + 3])[None]
        out = out + torch.einsum("bc,xco->bxo", c, w[:, d + 3 :])[:, :, None, :]
        out = out + net.bias[None, :, None, :]
        return out.reshape(1, *grid, -1).permute(0, 4, 1, 2, 3)

    with torch.no_grad():
        ref = by_design()
        diff = max(float((f() - ref).abs().max()) for f in (lambda: net(x, coords, c), by_stencil))
        conv = best_ms(lambda: net(x, coords, c))
        stacked = best_ms(by_stencil)
        design = best_ms(by_design)
    print(
        f"ridge on {grid[0]} x {grid[1]} x {grid[2]} bins, {channels} channels, {outputs} outputs, "
        f"{args.threads} thread(s): forward (grouped convolution) {conv:.2f} ms; stacked "
        f"stencil x weights {stacked:.2f} ms ({stacked / conv:.1f}x); design rows x weights "
        f"{design:.2f} ms ({design / conv:.1f}x); largest difference {diff:.2g} (outputs up to "
        f"{float(ref.abs().max()):.3g})"
    )


if __name__ == "__main__":
    main()
