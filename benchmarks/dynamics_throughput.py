"""Training time and per-step inference latency of each field-evolution model on a sweep's
training stores.

    python benchmarks/dynamics_throughput.py --results results [--config config/config.yaml] \\
        [--threads 1] [--models persistence ridge unet] [--device cpu]

Trains every model as the workflow's ``train_dynamics`` job does (the config's ``dynamics`` and
the ``learn`` early-stopping blocks) on the sweep's training points under ``--results`` and
prints its wall time, then the latency of one call (batch 1: one sweep point stepped ahead
``horizon`` rows) and of a batch of 16 calls, per predicted row; on CUDA too when present (or
asked for with ``--device``). Accuracy is the validate-dynamics job's, not this script's.
"""

from __future__ import annotations

import argparse
import time

import torch

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.learn.data import load_store
from dozerlab.learn.dynamics.models import DYNAMICS_MODELS, DynamicsModel
from dozerlab.learn.dynamics.train import train_dynamics
from dozerlab.runtime import set_threads


@torch.no_grad()
def latency(
    model: DynamicsModel, store, device: torch.device, batch: int, repeats: int = 30
) -> float:  # type: ignore[no-untyped-def]
    """Seconds per predicted row of one call on ``batch`` windows (best of 3 timings)."""
    model = model.to(device).eval()
    h, m = model.history, model.horizon
    args = [
        torch.from_numpy(a[None, :n]).expand(batch, *a[:n].shape).contiguous().to(device)
        for a, n in ((store.velocity, h), (store.density, h), (store.blade_velocity, h + m))
    ]
    model(*args)
    best = float("inf")
    for _ in range(3):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        for _ in range(repeats):
            model(*args)
        if device.type == "cuda":
            torch.cuda.synchronize()
        best = min(best, (time.perf_counter() - t0) / repeats / m)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results", help="results directory holding fields/")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--models", nargs="+", default=list(DYNAMICS_MODELS), choices=DYNAMICS_MODELS)
    ap.add_argument("--device", default=None, help="torch device for training (default: cpu)")
    args = ap.parse_args()
    set_threads(args.threads)
    cfg = load_config(args.config)
    train = [P.field_path(args.results, p) for p in P.by_role(P.sweep_points(cfg), "train")]
    stores = [load_store(p) for p in train]
    rows = sum(s.density.shape[0] for s in stores)
    print(
        f"{len(stores)} training stores, {rows} rows, grid {stores[0].grid}, threads {args.threads}"
    )
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    for kind in args.models:
        t0 = time.perf_counter()
        result = train_dynamics(kind, stores, cfg, device=args.device or "cpu", progress=False)
        wall = time.perf_counter() - t0
        epochs = len(result.train_loss)
        print(
            f"{kind:12s} training {wall:7.1f} s wall ({result.seconds:.1f} s fitting, {epochs} epoch(s))"
        )
        for dev in devices:
            one = latency(result.model, stores[0], dev, 1)
            many = latency(result.model, stores[0], dev, 16)
            print(
                f"{'':12s} {dev.type}: {1e3 * one:7.2f} ms per row (batch 1), {1e3 * many / 16:7.3f} ms per row and window (batch 16)"
            )


if __name__ == "__main__":
    main()
