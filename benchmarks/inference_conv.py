"""One-sample inference of the networks the reduced loop calls each step: every 3D convolution
of the evolution U-Net and of the force models' U-Net and CNN, torch's own dispatch beside
oneDNN's convolution called directly, and each whole network both ways; and the evolution
ridge's linear map against its design rows times its weights; in one process.

    python benchmarks/inference_conv.py [--config config/config.yaml] [--threads 1] [--repeats 300]

The networks are built with random weights on the config's grid (``sampling.bins``) with the config's
histories (``learn.history``, ``dynamics.history`` and ``horizon``): the time of a convolution
does not depend on its weights. For each convolution it prints its shape, its im2col columns
(input channels × kernel volume × output bins), µs per call on torch's path and on oneDNN's, and
which :class:`dozerlab.learn.models.Conv3d` takes (``ONEDNN_COLUMNS``); then ms per forward of
each network with every convolution on torch's path and with ``Conv3d``'s choice, and the
largest difference of their outputs. For the ridge (its stencil stacked from 27 shifted views,
the position's and the control's terms added by parts): ms per forward, per building the design
rows the closed-form fit reads, and per those rows times the weights (the baseline: what forward
computed before), with the largest difference of the two.
Not a test: the seconds depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import torch

from dozerlab.config import load_config
from dozerlab.learn import models as M
from dozerlab.learn.dynamics.models import DynamicsModel, RidgeStencil


def _us(f: Callable[[], object], repeats: int) -> float:
    for _ in range(max(repeats // 10, 5)):
        f()
    t = time.perf_counter()
    for _ in range(repeats):
        f()
    return 1e6 * (time.perf_counter() - t) / repeats


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
    lh, dh, dm = (
        int(config["learn"]["history"]),
        int(config["dynamics"]["history"]),
        int(config["dynamics"]["horizon"]),
    )
    evolution = DynamicsModel("unet", grid, dh, dm, 0.01, (0.05, 0.05, 0.05)).eval()
    assert evolution.net is not None
    nets: dict[str, tuple[torch.nn.Module, tuple[torch.Tensor, ...]]] = {
        "evolution unet": (
            evolution.net,
            (
                torch.randn(1, 4 * (dh + dm), *grid),
                evolution.coords,
                torch.randn(1, 3 * (dh + dm)),
            ),
        ),
    }
    for kind in ("unet", "cnn"):
        force = M.ForceModel(kind, grid, lh).eval()
        nets[f"force {kind}"] = (
            force.backbone,
            (torch.randn(1, M.n_channels(lh), *grid), torch.randn(1, 3 * lh)),
        )
    for net, _ in nets.values():  # random weights: the untrained evolution U-Net outputs zeros
        for p in net.parameters():
            torch.nn.init.normal_(p, std=0.1)
    threshold = M.ONEDNN_COLUMNS
    print(f"{args.threads} thread(s), grid {grid}, one sample; ONEDNN_COLUMNS = {threshold}")
    with torch.inference_mode():
        for name, (net, inputs) in nets.items():
            seen: list[tuple[M.Conv3d, torch.Tensor]] = []
            hooks = [
                m.register_forward_pre_hook(lambda m, a, s=seen: s.append((m, a[0])))
                for m in net.modules()
                if isinstance(m, M.Conv3d)
            ]
            net(*inputs)
            for h in hooks:
                h.remove()
            print(f"\n{name}: {len(seen)} convolutions")
            for conv, x in seen:
                eager = _us(lambda c=conv, x=x: torch.nn.Conv3d.forward(c, x), args.repeats)
                onednn = _us(
                    lambda c=conv, x=x: torch.ops.aten.mkldnn_convolution(
                        x, c.weight, c.bias, c.padding, c.stride, c.dilation, c.groups
                    ),
                    args.repeats,
                )
                k = conv.kernel_size
                bins = x[0, 0].numel() // (conv.stride[0] * conv.stride[1] * conv.stride[2])
                cols = x.shape[1] * k[0] * k[1] * k[2] * bins
                took = "oneDNN" if conv.uses_onednn(x) else "torch"
                print(
                    f"  {x.shape[1]:3d}->{conv.out_channels:3d} k{k[0]} s{conv.stride[0]} on "
                    f"{tuple(x.shape[2:])}: {cols:7d} columns, torch {eager:6.0f} us, "
                    f"oneDNN {onednn:6.0f} us -> {took}"
                )
            M.ONEDNN_COLUMNS = 10**18
            plain = _us(lambda n=net, i=inputs: n(*i), args.repeats) / 1e3
            ref = net(*inputs)
            M.ONEDNN_COLUMNS = threshold
            chosen_ms = _us(lambda n=net, i=inputs: n(*i), args.repeats) / 1e3
            diff = float((net(*inputs) - ref).abs().max())
            print(
                f"  whole network: torch's path {plain:.2f} ms, Conv3d's choice {chosen_ms:.2f} "
                f"ms ({plain / chosen_ms:.2f}x); outputs differ by {diff:.1e}"
            )
        _ridge(grid, dh, dm, args.repeats)


def _ridge(grid: tuple[int, ...], history: int, horizon: int, repeats: int) -> None:
    """The ridge's forward against its design rows times its weights (random weights)."""
    model = DynamicsModel("ridge", grid, history, horizon, 0.01, (0.05, 0.05, 0.05)).eval()
    net = model.net
    assert isinstance(net, RidgeStencil)
    torch.nn.init.normal_(net.weight)
    torch.nn.init.normal_(net.bias)
    x = torch.randn(1, 4 * (history + horizon), *grid)
    c = torch.randn(1, 3 * (history + horizon))

    def by_rows() -> torch.Tensor:
        rows = net.design(x, model.coords, c)
        return torch.einsum("bxnd,xdo->bxno", rows, net.weight) + net.bias[None, :, None, :]

    forward = _us(lambda: net(x, model.coords, c), repeats) / 1e3
    design = _us(lambda: net.design(x, model.coords, c), repeats) / 1e3
    baseline = _us(by_rows, repeats) / 1e3
    got = net(x, model.coords, c).permute(0, 2, 3, 4, 1).flatten(1, 3)
    want = by_rows().flatten(1, 2)
    print(
        f"\nevolution ridge: forward {forward:.2f} ms; design rows {design:.2f} ms, times the "
        f"weights {baseline:.2f} ms ({baseline / forward:.2f}x); outputs differ by "
        f"{float((got - want).abs().max()):.1e} (up to {float(want.abs().max()):.3g})"
    )


if __name__ == "__main__":
    main()
