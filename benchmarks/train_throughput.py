"""Training throughput, inference latency and data-wait fraction of each model.

    python benchmarks/train_throughput.py [--grid 24 20 12] [--steps 400] [--stores 4] [--epochs 2] [--threads 2]

Synthetic stores of the default grid (random fields, force a function of them) stand in for a
sweep; figures are per device (CPU, and CUDA when present). "data wait" is the fraction of a
training step spent gathering the batch from the in-memory tensors (target < 10 %).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from dozerlab.config import load_config
from dozerlab.learn.data import from_arrays
from dozerlab.learn.names import MODEL_NAMES
from dozerlab.learn.train import train_model
from dozerlab.runtime import set_threads


def synthetic(grid: tuple[int, int, int], steps: int, seed: int):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    density = rng.uniform(0, 2000, (steps, *grid)).astype(np.float32)
    velocity = rng.normal(0, 0.5, (steps, *grid, 3)).astype(np.float32)
    vb = np.tile(np.float32([1.0, 0, 0]), (steps, 1))
    mass = density.sum(axis=(1, 2, 3))[:, None] * 1e-4
    return from_arrays(
        velocity,
        density,
        vb,
        mass * [1, 0.1, 0.5],
        mass * [0.2, -0.3, 0.05],
        point={"scenario": "hill", "speed": 1.0, "depth": 0.05 * (seed + 1)},
    )


@torch.no_grad()
def latency(model: torch.nn.Module, store, device: torch.device, repeats: int = 20) -> float:  # type: ignore[no-untyped-def]
    """Seconds per single-step prediction (batch of 1, with the model's history)."""
    model = model.to(device).eval()
    h = model.history  # one prediction: the current step and its history
    args = [
        torch.from_numpy(a[None, :h]).to(device)
        for a in (store.velocity, store.density, store.blade_velocity)
    ]
    model(*args)
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(repeats):
        model(*args)
    if device.type == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - t0) / repeats


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--grid", type=int, nargs=3, default=[24, 20, 12])
    p.add_argument("--steps", type=int, default=400, help="steps per synthetic store")
    p.add_argument("--stores", type=int, default=4)
    p.add_argument("--epochs", type=int, default=2)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--models", nargs="+", default=list(MODEL_NAMES), choices=MODEL_NAMES)
    args = p.parse_args()
    set_threads(args.threads)
    stores = [synthetic(tuple(args.grid), args.steps, k) for k in range(args.stores)]
    config = load_config({"learn": {"epochs": args.epochs, "patience": args.epochs}})
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    print(
        f"grid {tuple(args.grid)}, {args.stores}×{args.steps} steps, {args.epochs} epochs, {args.threads} threads, "
        f"history {config['learn']['history']}"
    )
    print(f"{'model':8s} {'device':6s} {'samples/s':>10s} {'data wait':>10s} {'latency/step':>13s}")
    for device in devices:
        for kind in args.models:
            r = train_model(kind, stores, config, device=device, progress=False)
            epochs = len(r.train_loss) if kind != "linear" else 1
            rate = r.samples["train"] * epochs / r.seconds
            wait = r.data_seconds / r.seconds if kind != "linear" else 0.0
            lat = latency(r.model, stores[0], torch.device(device))
            print(
                f"{kind:8s} {device:6s} {rate:10.0f} {100 * wait:9.1f}% {1e3 * lat:10.2f} ms",
                flush=True,
            )


if __name__ == "__main__":
    main()
