"""The ridge evolution model's forward pass against its design rows times its weights, in one
process: what one reduced step's field inference costs in the linear map itself.

    python benchmarks/ridge_stencil.py [--config config/config.yaml] [--threads 1] [--repeats 300]

Builds a ridge :class:`dozerlab.learn.dynamics.models.DynamicsModel` with random weights on the
config's grid (``sampling.bins``) and histories (``dynamics.history``, ``horizon``): the time of
a linear map does not depend on its weights. Prints ms per call of the network's ``forward``
(the stencil stacked from 27 shifted views, the position's and the control's terms added by
parts), of the design rows the closed-form fit reads (``design``) and of those rows times the
weights (the forward of before, the baseline), of the whole model (advection base, inputs,
network, correction), and the largest difference between the two outputs.
Not a test: the seconds depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import torch

from dozerlab.config import load_config
from dozerlab.learn.dynamics.models import DynamicsModel, RidgeStencil


def _ms(f: Callable[[], object], repeats: int) -> float:
    for _ in range(max(repeats // 10, 5)):
        f()
    t = time.perf_counter()
    for _ in range(repeats):
        f()
    return 1e3 * (time.perf_counter() - t) / repeats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=300)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    config = load_config(args.config)
    grid = tuple(int(n) for n in config["sampling"]["bins"])
    h, m = int(config["dynamics"]["history"]), int(config["dynamics"]["horizon"])
    model = DynamicsModel("ridge", grid, h, m, 0.01, (0.05, 0.05, 0.05)).eval()
    net = model.net
    assert isinstance(net, RidgeStencil)
    with torch.no_grad():
        net.weight.normal_()
        net.bias.normal_()
        x = torch.randn(1, 4 * (h + m), *grid)
        c = torch.randn(1, 3 * (h + m))
        v, rho = torch.randn(1, h, *grid, 3), torch.rand(1, h, *grid) * 1600
        vb = torch.zeros(1, h + m, 3)
        vb[..., 0] = 1.0

        def by_rows() -> torch.Tensor:
            rows = net.design(x, model.coords, c)
            return torch.einsum("bxnd,xdo->bxno", rows, net.weight) + net.bias[None, :, None, :]

        got = net(x, model.coords, c).permute(0, 2, 3, 4, 1).flatten(1, 3)
        want = by_rows().flatten(1, 2)
        print(f"grid {grid}, history {h}, horizon {m}, threads {args.threads}")
        timed: list[tuple[str, Callable[[], object]]] = [
            ("forward (stacked stencil, by parts)", lambda: net(x, model.coords, c)),
            ("design rows", lambda: net.design(x, model.coords, c)),
            ("design rows x weights (baseline)", by_rows),
            ("whole model (base, inputs, correct)", lambda: model(v, rho, vb)),
        ]
        for label, f in timed:
            print(f"  {label:38s} {_ms(f, args.repeats):6.3f} ms")
        print(
            f"  {'largest |forward - rows x weights|':38s} {float((got - want).abs().max()):.3g} "
            f"(outputs up to {float(want.abs().max()):.3g})"
        )


if __name__ == "__main__":
    main()
