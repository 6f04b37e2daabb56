"""Held-out validation: metrics per sweep point, per group and overall, and their plots.

The result is a JSON document and PNG files; the platform's report (``dozerlab.report``) reads
them and builds its HTML.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.learn import plots
from dozerlab.learn.data import StoreData, check_grid, load_store, point_key
from dozerlab.learn.metrics import component_metrics
from dozerlab.learn.models import ForceModel
from dozerlab.learn.pyfunc import predict_arrays
from dozerlab.runtime import DozerlabError
from dozerlab.sweep import HELD_OUT_ROLES, SweepPoint

GROUPS = HELD_OUT_ROLES


def predict_store(model: ForceModel, store: StoreData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Time (s), predicted and measured (T', 6) force/torque of the steps with a full history."""
    pred = predict_arrays(
        model,
        {
            "velocity": store.velocity,
            "density": store.density,
            "blade_velocity": store.blade_velocity,
        },
    )
    k = model.history - 1
    return store.time[k:], pred[k:], store.target[k:]


def check_no_leak(meta: dict[str, Any], stores: list[StoreData]) -> None:
    """Refuse held-out stores whose sweep point (or file) the model was trained on."""
    # keys of models saved before the sweep's identity were (scenario, speed, depth)
    trained = {
        SweepPoint(str(p[0]), float(p[1]), float(p[2])).key if len(p) == 3 else tuple(p)
        for p in meta.get("train_keys", [])
    }
    sources = {str(Path(s).resolve()) for s in meta.get("train_sources", [])}
    for s in stores:
        key = point_key(s.point)
        if (key is not None and key in trained) or (
            s.source and str(Path(s.source).resolve()) in sources
        ):
            raise DozerlabError(
                f"held-out store {s.source or s.name} is the sweep point {s.name}, which the model was "
                "trained on; held-out points must not be training points"
            )


def evaluate(model: ForceModel, stores: list[StoreData]) -> dict[str, Any]:
    """Metrics of ``model`` on each store and over all of them (no plots, no checks of leaks)."""
    check_grid(stores, model.grid, blade_part=model.blade_part)
    points, preds, trues = [], [], []
    for s in stores:
        t, pred, true = predict_store(model, s)
        points.append(
            {
                "name": s.name,
                "point": s.point,
                "store": s.source,
                "steps": len(t),
                "metrics": component_metrics(pred, true),
                "_series": (t, pred, true),
            }
        )
        preds.append(pred)
        trues.append(true)
    overall = component_metrics(np.concatenate(preds), np.concatenate(trues))
    return {"points": points, "overall": overall}


def strip_series(points: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in p.items() if not k.startswith("_")} for p in points]


def summary_line(kind: str, groups: dict[str, Any]) -> str:
    """One line: the model's force_x relative RMSE and R² per group."""
    parts = []
    for g in GROUPS:
        if g in groups:
            m = groups[g]["overall"]["force_x"]
            parts.append(f"{g} force_x rel. RMSE {100 * m['rel_rmse']:.1f} %, R² {m['r2']:.3f}")
    return f"{kind}: " + "; ".join(parts)


def validate(
    model: ForceModel,
    meta: dict[str, Any],
    held_out: dict[str, list[StoreData]],
    plots_dir: str | Path | None = None,
    json_dir: str | Path | None = None,
    plots_at: str | Path | None = None,
) -> dict[str, Any]:
    """Validate on held-out stores grouped as ``{"interpolation": [...], "extrapolation": [...],
    "transfer": [...]}`` (any may be missing).

    Writes plots into ``plots_dir`` when given; their paths in the result are those in
    ``plots_at`` (where that folder will be moved; default ``plots_dir``), relative to
    ``json_dir`` (where the JSON will live). Raises DozerlabError on a grid mismatch or a
    held-out point that was a training point.
    """
    stores = [s for g in GROUPS for s in held_out.get(g, [])]
    if not stores:
        raise ValueError("no held-out stores given (--interpolation, --extrapolation, --transfer)")
    check_grid(stores, model.grid, meta.get("bin_size"), blade_part=model.blade_part)
    check_no_leak(meta, stores)
    groups = {g: evaluate(model, held_out[g]) for g in GROUPS if held_out.get(g)}
    allpts = [p for g in groups.values() for p in g["points"]]
    result: dict[str, Any] = {
        "model": model.kind,
        "trained_on": meta.get("train_points", []),
        "overall": component_metrics(
            np.concatenate([p["_series"][1] for p in allpts]),
            np.concatenate([p["_series"][2] for p in allpts]),
        ),
        "groups": {
            g: {"overall": v["overall"], "points": strip_series(v["points"])}
            for g, v in groups.items()
        },
        "summary": summary_line(model.kind, groups),
        "training": {
            "epochs": len(meta.get("train_loss", [])),
            "best_epoch": meta.get("best_epoch"),
            "samples": meta.get("samples"),
            "seconds": meta.get("seconds"),
        },
        "plots": {},
    }
    if plots_dir is not None:
        result["plots"] = _make_plots(
            model.kind, meta, groups, Path(plots_dir), Path(json_dir or plots_dir), plots_at
        )
    return result


def _make_plots(
    kind: str,
    meta: dict[str, Any],
    groups: dict[str, Any],
    pdir: Path,
    base: Path,
    plots_at: str | Path | None,
) -> dict[str, Any]:
    rel = lambda p: os.path.relpath(Path(plots_at or pdir) / Path(p).name, base)  # noqa: E731
    out: dict[str, Any] = {"series": {}}
    if meta.get("train_loss"):
        out["loss"] = rel(
            plots.loss_curves(
                meta["train_loss"], meta["val_loss"], pdir / "loss.png", f"{kind}: loss"
            )
        )
    pairs = {
        g: (
            np.concatenate([p["_series"][1] for p in v["points"]]),
            np.concatenate([p["_series"][2] for p in v["points"]]),
        )
        for g, v in groups.items()
    }
    out["parity"] = rel(plots.parity(pairs, pdir / "parity.png", f"{kind}: held-out points"))
    for g, v in groups.items():
        for i, p in enumerate(v["points"]):
            t, pred, true = p["_series"]
            path = plots.force_series(
                t, pred, true, pdir / f"{g}_{i:02d}.png", f"{kind}, {g}: {p['name']}"
            )
            out["series"][f"{g}: {p['name']}"] = rel(path)
    return out


def load_groups(
    interpolation: list[str | Path],
    extrapolation: list[str | Path],
    transfer: list[str | Path] | tuple[()] = (),
) -> dict[str, list[StoreData]]:
    """Load held-out stores by group (``transfer``: on unseen terrain)."""
    return {
        "interpolation": [load_store(p) for p in interpolation],
        "extrapolation": [load_store(p) for p in extrapolation],
        "transfer": [load_store(p) for p in transfer],
    }
