"""Figures of a reduced run next to its NDEM run: force, field errors, bed profile, where the
smoothed surface departs from NDEM's, animation.

The animation puts the two runs side by side, frame by frame: the middle y-slice of each store
(density as a heat map, in-plane velocity relative to the blade as arrows, as
``dozerlab plot-fields`` draws it) and, beneath, the bed's surface in the sampling volume of both
runs (per x, the height of the highest bin holding more than a third of the solid density,
averaged over y).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import xarray as xr
from matplotlib.figure import Figure

from dozerlab.fields.plots import _density_max, _Slice, write_gif
from dozerlab.runtime import FIGURE, atomic_output, png_metadata


def _save(fig: Figure, path: str | Path) -> Path:
    with atomic_output(path, FIGURE) as tmp:
        fig.savefig(tmp, format="png", dpi=110, metadata=png_metadata())
    return Path(path)


def _title(m: Mapping) -> str:
    return f"{m['scenario']}, v = {m['speed']} m/s, d = {m['depth']} m — {m['dynamics_model']}"


def plot_force(series: Mapping[str, np.ndarray], metrics: Mapping, path: str | Path) -> Path:
    """Pushing force (x) and |F| of both runs over time, given in N and drawn in kN, with the
    pushing force low-passed over ``force_window`` s (dashed) of both and, where the series hold
    it, of NDEM's twin; the warm-up rows (the evolution model's history) shaded."""
    from dozerlab.reduce.compare import low_pass

    fig = Figure(figsize=(9, 4.5), layout="constrained")
    ax = fig.add_subplot()
    t, warm = series["time"], int(series["warmup"])
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    window = float(series["force_window"])
    runs = [("force_ndem", "k", "NDEM"), ("force_reduced", "C3", "reduced")]
    if "force_twin" in series:
        runs.append(("force_twin", "C0", "NDEM's twin"))
    for key, colour, label in runs:
        force = series[key] / 1000.0
        if key != "force_twin":
            ax.plot(t, force[:, 0], color=colour, lw=1.0, label=f"{label} force x")
            ax.plot(t, np.linalg.norm(force, axis=1), color=colour, lw=0.6, alpha=0.4)
        ax.plot(
            t,
            low_pass(force[:, 0], dt, window),
            color=colour,
            ls="--",
            lw=1.6,
            label=f"{label} force x over {window:g} s",
        )
    if warm:
        ax.axvspan(t[0], t[warm - 1], color="0.85", label="warm-up (the model's history)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("force on the blade (kN); faint: |F|")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, ncol=3)
    title = f"{_title(metrics)}: force x rel. RMSE {metrics['force_x_rel_rmse']:.1%}"
    lp = metrics.get("force_lp_rel_rmse")
    if lp is not None:
        title += f", low-passed {lp:.1%}"
        if (twin := metrics.get("twin_force_lp_rel_rmse")) is not None:
            title += f" (the twin's {twin:.1%})"
    ax.set_title(title, fontsize=10)
    return _save(fig, path)


def plot_errors(series: Mapping[str, np.ndarray], metrics: Mapping, path: str | Path) -> Path:
    """L2 error of the velocity (mass-weighted) and density fields over time, each over the
    NDEM field's RMS row norm of the run."""
    fig = Figure(figsize=(9, 4), layout="constrained")
    ax = fig.add_subplot()
    ax.plot(series["time"], series["velocity_error"], label="velocity (mass-weighted)")
    ax.plot(series["time"], series["density_error"], label="density")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("L2 error vs NDEM / NDEM's RMS")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(_title(metrics), fontsize=10)
    return _save(fig, path)


def plot_height(series: Mapping[str, np.ndarray], metrics: Mapping, path: str | Path) -> Path:
    """The bed's height profile (mean over y) before and after the pass, both runs."""
    fig = Figure(figsize=(9, 4), layout="constrained")
    ax = fig.add_subplot()
    x = series["height_x"]
    ax.plot(x, series["height_bed"], color="0.6", label="bed before")
    ax.plot(x, series["height_ndem"], "k", label="NDEM after")
    ax.plot(x, series["height_reduced"], "C3--", label="reduced after")
    if "height_twin" in series:
        ax.plot(x, series["height_twin"], "C0:", label="NDEM's twin after")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("bed height, mean over y (m)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(
        f"{_title(metrics)}: height accuracy {metrics['height_accuracy']:.1%}", fontsize=10
    )
    return _save(fig, path)


def plot_surface(series: Mapping[str, np.ndarray], metrics: Mapping, path: str | Path) -> Path:
    """Where the smoothed surface departs from NDEM's: the run's surface minus NDEM's over the
    bed (mm, red too high, blue too low) and beneath it the twin's, on one colour scale, with
    the regions its error is split over (the blade's last tip position, the swath's edges) and
    each region's error in the panel's title."""
    from dozerlab.reduce.compare import SURFACE_REGIONS

    panels = [("reduced", "surface_reduced", "")]
    if "surface_twin" in series:
        panels.append(("NDEM's twin", "surface_twin", "twin_"))
    length, width = (float(v) for v in series["extent"])
    diffs = [1e3 * (series[key] - series["surface_ndem"]) for _, key, _ in panels]
    top = float(max(np.percentile(np.abs(d), 99.5) for d in diffs)) or 1.0
    tip, half = series["path"], 0.5 * float(series["blade_width"])
    behind = tip[:, 0] <= tip[-1, 0]
    fig = Figure(figsize=(9, 1.2 + 2.3 * len(panels)), layout="constrained")
    axes = fig.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
    for ax, (name, _, prefix), d in zip(axes, panels, diffs, strict=True):
        image = ax.imshow(
            d.T,
            origin="lower",
            extent=(0.0, length, -width / 2, width / 2),
            cmap="RdBu_r",
            vmin=-top,
            vmax=top,
            aspect="auto",
            interpolation="nearest",
        )
        for edge in (-half, half):
            ax.plot(tip[behind, 0], tip[behind, 1] + edge, "k--", lw=0.8)
        ax.axvline(tip[-1, 0], color="k", lw=0.8)
        ax.set_xlim(0.0, length)  # the path starts before the bed
        parts = ", ".join(
            f"{r} {metrics.get(f'{prefix}surface_error_{r}', float('nan')):.1%}"
            for r in SURFACE_REGIONS
        )
        ax.set_title(
            f"{name} − NDEM: accuracy {metrics.get(f'{prefix}surface_accuracy', float('nan')):.1%}"
            f"; error by region (of NDEM's change) {parts}",
            fontsize=9,
        )
        ax.set_ylabel("y (m)")
        fig.colorbar(image, ax=ax, label="height − NDEM's (mm)", shrink=0.9)
    axes[-1].set_xlabel("x (m); dashed: the swath's edges, solid: the blade's last tip position")
    fig.suptitle(f"{_title(metrics)}: smoothed surface against NDEM's", fontsize=10)
    return _save(fig, path)


def surface(ds: xr.Dataset, step: int, solid: float) -> np.ndarray:
    """Height (m, blade frame) of the material's top per x bin at row ``step``, (Nx,)."""
    rho = ds["density"].isel(time=step).values  # (Nx, Ny, Nz)
    z = ds["z"].values
    dz = float(z[1] - z[0]) if z.size > 1 else 0.0
    full = rho > solid / 3
    top = np.where(
        full.any(axis=2), z[np.argmax(np.cumsum(full, axis=2), axis=2)] + dz / 2, z[0] - dz / 2
    )
    return top.mean(axis=1)


def animate_pair(
    ndem: xr.Dataset, reduced: xr.Dataset, path: str | Path, *, frames: int = 40, fps: int = 6
) -> Path:
    """A GIF of NDEM (left) next to the reduced run (right), ``frames`` rows spread over the run."""
    n = ndem.sizes["time"]
    rows = np.unique(np.linspace(0, n - 1, min(frames, n)).round().astype(int))
    vmax = max(_density_max(ndem), _density_max(reduced))
    # the frames' rows read once, not a chunk decoded again for every frame
    ndem, reduced = (ds.isel(time=rows).load() for ds in (ndem, reduced))
    fig = Figure(figsize=(13, 7))
    # subfigures(n, m) returns an array of n·m subfigures; matplotlib's stub says one
    top, bottom = fig.subfigures(2, 1, height_ratios=[3, 1.4])  # type: ignore[misc]
    left, right = top.subfigures(1, 2)
    views = [_Slice(left, ndem, vmax), _Slice(right, reduced, vmax)]
    ax = bottom.add_subplot()
    x = ndem["x"].values
    (line_n,) = ax.plot(x, np.zeros_like(x), "k-", label="NDEM")
    (line_r,) = ax.plot(x, np.zeros_like(x), "C3--", label="reduced")
    ax.set_xlim(views[0].ax.get_xlim())
    z = ndem["z"].values
    ax.set_ylim(z[0] - (z[1] - z[0]), z[-1] + (z[1] - z[0]))
    ax.set_xlabel("x in front of the blade (m)")
    ax.set_ylabel("surface z (m)")
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(alpha=0.3)
    warm = int(reduced.attrs.get("warmup_rows", 0))

    def show(s: int) -> None:
        for view, name in zip(views, ("NDEM", "reduced"), strict=True):
            view.show(s)
            phase = " (warm-up)" if name == "reduced" and rows[s] < warm else ""
            view.ax.set_title(
                f"{name}{phase}, t = {float(ndem['time'].values[s]):.2f} s", fontsize=9
            )
        line_n.set_ydata(surface(ndem, s, vmax))
        line_r.set_ydata(surface(reduced, s, vmax))

    show(0)
    # the legend last: it stays above the lines, as in a full draw
    animated = [a for view in views for a in view.artists] + [line_n, line_r, ax.get_legend()]
    # dpi 60: ≈1 MB a point, and the report embeds several
    return write_gif(fig, show, animated, range(len(rows)), path, fps=fps, dpi=60)
