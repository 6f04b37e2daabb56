"""Where a force model's error on unseen terrain lies: the whole run against a stretch of it.

    python benchmarks/transfer_split.py --results results --store results/fields/trench/speed~1.0_depth~0.06.zarr \
        --models linear cnn unet --window 2.0 2.6

For each model, the relative RMSE of the pushing force ``force_x`` (the validate metric,
RMSE over the RMS of NDEM's force) over the whole run, over the run without the rows whose time
lies in ``--window`` (s; on the default config's trench, where the blade crosses it), and the
share of the squared error that those rows hold.
"""

from __future__ import annotations

import argparse

import numpy as np

from dozerlab.learn import pyfunc
from dozerlab.learn.data import load_store
from dozerlab.learn.validate import predict_store
from dozerlab.sweep import model_path


def rel_rmse(pred: np.ndarray, true: np.ndarray) -> float:
    """RMSE of ``pred`` against ``true`` over the RMS of ``true`` (same units, here N)."""
    return float(np.sqrt(np.mean((pred - true) ** 2)) / np.sqrt(np.mean(true**2)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", default="results", help="the results folder of the models")
    parser.add_argument("--store", required=True, help="the field store of the held-out run")
    parser.add_argument("--models", nargs="+", default=["linear", "cnn", "unet"])
    parser.add_argument("--window", nargs=2, type=float, required=True, metavar=("T0", "T1"))
    args = parser.parse_args()
    store = load_store(args.store)
    t0, t1 = args.window
    for name in args.models:
        model, _ = pyfunc.load(model_path(args.results, name))
        t, pred, true = predict_store(model, store)
        fx, tx = pred[:, 0], true[:, 0]
        inside = (t >= t0) & (t <= t1)
        share = np.sum((fx[inside] - tx[inside]) ** 2) / np.sum((fx - tx) ** 2)
        print(
            f"{name}: force_x rel. RMSE {100 * rel_rmse(fx, tx):.1f} % over the run, "
            f"{100 * rel_rmse(fx[~inside], tx[~inside]):.1f} % without t in [{t0:g}, {t1:g}] s "
            f"({inside.sum()} of {len(t)} rows, {100 * share:.0f} % of the squared error)"
        )


if __name__ == "__main__":
    main()
