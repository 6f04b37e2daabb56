"""The force and evolution models trained with glibc's malloc as it comes and with the freed
memory kept (``dozerlab.runtime.keep_freed_memory``, which the training jobs call), side by
side in fresh processes, one thread each.

    python benchmarks/freed_memory.py --results results --models mlp cnn unet --epochs 2
    python benchmarks/freed_memory.py --results results --dynamics unet --epochs 2

Each model is trained on the sweep's training points (the config's grid: ``sweep.scenarios`` ×
``speeds`` × ``depths``, read from ``RESULTS/fields``) for ``--epochs`` epochs in a process of
its own, the two settings alternately, ``--repeat`` times. Printed per run: the seconds of the
training itself (``TrainResult.seconds``), the seconds of the whole process's work (loading the
stores included) and a hash of the trained weights, which must be the same in both settings;
then the medians' ratio. Not a test: the seconds depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

WORKER = r"""
import hashlib, json, sys, time
from dozerlab.runtime import keep_freed_memory, set_threads
kept = sys.argv[1] == "kept" and keep_freed_memory()
set_threads(1)
t0 = time.perf_counter()
from dozerlab.config import load_config
from dozerlab.learn.data import load_store
family, kind, epochs, config_path = sys.argv[2], sys.argv[3], int(sys.argv[4]), sys.argv[5]
paths = json.loads(sys.argv[6])
config = load_config(config_path)
section = "learn" if family == "force" else "dynamics"
config[section] = {**config[section], "epochs": epochs}
stores = [load_store(p) for p in paths]
if family == "force":
    from dozerlab.learn.train import train_model as train
else:
    from dozerlab.learn.dynamics.train import train_dynamics as train
result = train(kind, stores, config, progress=False)
digest = hashlib.sha256()
for key, value in sorted(result.model.state_dict().items()):
    digest.update(value.detach().cpu().numpy().tobytes())
print(json.dumps({"kept": kept, "train_s": result.seconds, "all_s": time.perf_counter() - t0,
                  "weights": digest.hexdigest()[:16]}))
"""


def training_stores(results: Path, config: dict) -> list[str]:  # type: ignore[type-arg]
    """The training points' field stores under ``results/fields``, in the grid's order."""
    from dozerlab.sweep import point_name

    sweep = config["sweep"]
    paths = [
        results / "fields" / scenario / f"{point_name(speed, depth)}.zarr"
        for scenario in sweep["scenarios"]
        for speed in sweep["speeds"]
        for depth in sweep["depths"]
    ]
    missing = [str(p) for p in paths if not p.is_dir()]
    if missing:
        raise SystemExit(f"missing training stores (run the sweep first): {', '.join(missing)}")
    return [str(p) for p in paths]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=Path("results"))
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--models", nargs="*", default=[], help="force models (learn.models)")
    ap.add_argument("--dynamics", nargs="*", default=[], help="evolution models")
    ap.add_argument("--epochs", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args(argv)

    from dozerlab.config import load_config

    stores = json.dumps(training_stores(args.results, load_config(args.config)))
    runs = [("force", kind) for kind in args.models] + [
        ("dynamics", kind) for kind in args.dynamics
    ]
    for family, kind in runs:
        seen: dict[str, list[dict]] = {"default": [], "kept": []}  # type: ignore[type-arg]
        for _ in range(args.repeat):
            for mode in seen:
                out = subprocess.run(
                    [sys.executable, "-c", WORKER, mode, family, kind, str(args.epochs)]
                    + [args.config, stores],
                    check=True,
                    capture_output=True,
                    text=True,
                ).stdout
                run = json.loads(out.strip().splitlines()[-1])
                seen[mode].append(run)
                print(
                    f"{family} {kind:6s} {mode:8s} training {run['train_s']:7.1f} s, in all "
                    f"{run['all_s']:7.1f} s, weights {run['weights']}",
                    flush=True,
                )
        same = {r["weights"] for runs_ in seen.values() for r in runs_}
        train = {m: statistics.median(r["train_s"] for r in rs) for m, rs in seen.items()}
        whole = {m: statistics.median(r["all_s"] for r in rs) for m, rs in seen.items()}
        print(
            f"{family} {kind}: kept / default, training {train['kept'] / train['default']:.2f}, "
            f"in all {whole['kept'] / whole['default']:.2f}; weights "
            f"{'the same' if len(same) == 1 else 'DIFFERENT'}",
            flush=True,
        )


if __name__ == "__main__":
    main()
