"""A linear force model's rows after the reduced loop, side by side: through the module in
batches (``learn.pyfunc.predict_arrays``, as every other force model's) and from the fields'
column sums (``learn.inference.LinearForceRows``, the loop's path for a linear model).

    python benchmarks/force_rows.py --model results/reduced/ridge/force_model \\
        --store results/fields/step/speed~1.0_depth~0.12.zarr [--rows 303] [--threads 1]

Reads the store's first ``--rows`` rows (the fields as the loop holds them: float32), makes a
first call of each path, then prints the ms of each over five calls (best, median) and the
largest difference of their forces and torques against the largest value of each.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from dozerlab.fields.store import open_store
from dozerlab.learn.inference import LinearForceRows
from dozerlab.learn.pyfunc import FORMAT, predict_arrays
from dozerlab.reduce.models import FORCE_BATCH
from dozerlab.runtime import set_threads


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="a linear force model's directory")
    ap.add_argument("--store", required=True, help="a field store (NDEM's or a reduced run's)")
    ap.add_argument("--rows", type=int, default=303)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    set_threads(args.threads)
    module, _ = FORMAT.load(args.model)
    store = open_store(args.store)
    n = min(args.rows, store.sizes["time"])
    velocity = store["velocity"].values[:n].astype(np.float32)
    density = store["density"].values[:n].astype(np.float32)
    blade = store["blade_velocity"].values[:n].astype(np.float64)
    arrays: dict[str, np.ndarray] = {
        "velocity": velocity,
        "density": density,
        "blade_velocity": blade,
    }
    rows = LinearForceRows(module)
    paths = {
        f"module, batches of {FORCE_BATCH}": lambda: predict_arrays(
            module, arrays, batch=FORCE_BATCH
        ),
        "column sums": lambda: rows(velocity, density, blade),
    }
    out = {}
    print(f"{args.model}: history {module.history}, contact {module.contact}, {n} rows")
    for name, call in paths.items():
        out[name] = np.asarray(call(), dtype=np.float64)
        ms = []
        for _ in range(5):
            t0 = time.perf_counter()
            call()
            ms.append(1e3 * (time.perf_counter() - t0))
        print(f"  {name}: best {min(ms):.2f} ms, median {float(np.median(ms)):.2f} ms")
    a, b = out.values()
    scale = np.abs(a).max(axis=0)
    diff = np.abs(a - b).max(axis=0)
    print(
        "  largest difference / largest value, per output: "
        + ", ".join(f"{d:.3g} / {s:.4g}" for d, s in zip(diff, scale, strict=True))
    )


if __name__ == "__main__":
    main()
