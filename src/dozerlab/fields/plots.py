"""Figures of a field store: x–z slices (after the thesis's figures 4.1–4.2), force series, GIFs.

A slice is the y-plane through the middle of the sampling volume: density as a heat map and the
in-plane (x, z) velocity relative to the blade as arrows, with the blade drawn at the left edge.
Figures use matplotlib's object API (no pyplot state), so they are safe in worker processes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import xarray as xr
from matplotlib.artist import Artist
from matplotlib.figure import Figure

from dozerlab.fields.store import store_config
from dozerlab.runtime import ANIMATION, FIGURE, MARK, atomic_output, marked_folder, png_metadata

#: What ``plot-fields`` and ``simulate --plots`` write: a folder of a store's figures.
FIELD_PLOTS = marked_folder("a dozerlab folder of field plots", "field-plots")


def _blade_size(ds: xr.Dataset) -> tuple[float, float]:
    """(thickness, height) of the blade in m, from the store's config or the volume's extent."""
    blade = store_config(ds).get("blade", {})
    x = ds["x"].values
    top = (
        float(ds["z"].values[-1] + (ds["z"].values[-1] - ds["z"].values[-2]) / 2)
        if ds.sizes["z"] > 1
        else 0.0
    )
    return float(blade.get("thickness", 0.04 * (x[-1] - x[0] + 1e-9))), float(
        blade.get("height", max(top, 0.0))
    )


class _Slice:
    """A figure of the middle y-slice whose data are swapped per step (cheap animation frames)."""

    def __init__(self, fig: Figure, ds: xr.Dataset, vmax: float) -> None:
        self.ds, self.fig = ds, fig
        self.j = ds.sizes["y"] // 2
        x, z = ds["x"].values, ds["z"].values
        ax = self.ax = fig.add_subplot()
        self.mesh = ax.pcolormesh(
            x, z, np.zeros((z.size, x.size)), shading="nearest", cmap="viridis", vmin=0.0, vmax=vmax
        )
        fig.colorbar(self.mesh, ax=ax, label="density (kg/m³)")
        xx, zz = np.meshgrid(x, z, indexing="ij")
        self.arrows = ax.quiver(
            xx.ravel(),
            zz.ravel(),
            np.zeros(xx.size),
            np.zeros(xx.size),
            color="white",
            angles="xy",
            scale_units="xy",
            scale=None,
            width=0.003,
        )
        thickness, height = _blade_size(ds)
        ax.fill_between([-thickness, 0.0], 0.0, height, color="0.4", label="blade")
        ax.set_xlim(-thickness, x[-1] + (x[-1] - x[-2] if x.size > 1 else thickness) / 2)
        ax.set_aspect("equal")
        ax.set_xlabel("x in front of the blade (m)")
        ax.set_ylabel("z above the blade tip (m)")

    @property
    def artists(self) -> list[Artist]:
        """What :meth:`show` changes: the density map, the arrows and the title."""
        return [self.mesh, self.arrows, self.ax.title]

    def show(self, step: int) -> None:
        ds, j = self.ds, self.j
        rho = ds["density"].isel(time=step, y=j).values  # (Nx, Nz)
        rel = (
            ds["velocity"].isel(time=step, y=j).values - ds["blade_velocity"].isel(time=step).values
        )
        rel[rho <= 0] = 0.0  # no arrows in empty bins
        self.mesh.set_array(rho.T.ravel())
        self.arrows.set_UVC(rel[..., 0].ravel(), rel[..., 2].ravel())
        t = float(ds["time"].values[step])
        self.ax.set_title(
            f"t = {t:.2f} s, y = {float(ds['y'].values[j]):+.3f} m; "
            "arrows: velocity relative to the blade",
            fontsize=11,
        )


def _density_max(ds: xr.Dataset) -> float:
    rho = ds["density"]
    peak = float(rho.isel(time=slice(None, None, max(1, ds.sizes["time"] // 50))).max())
    return peak if peak > 0 else 1.0


def plot_slice(ds: xr.Dataset, step: int, path: str | Path) -> Path:
    """Write a PNG of the middle y-slice at time index ``step`` (0 <= step < T)."""
    n = ds.sizes["time"]
    if not -n <= step < n:
        raise ValueError(f"step must be in [0, {n}) for a store of {n} steps, got {step}")
    fig = Figure(figsize=(9, 5), layout="constrained")
    _Slice(fig, ds, _density_max(ds)).show(step % n)
    with atomic_output(path, FIGURE) as tmp:
        fig.savefig(tmp, format="png", dpi=110, metadata=png_metadata())
    return Path(path)


def plot_force(ds: xr.Dataset, path: str | Path) -> Path:
    """Write a PNG of the blade force (kN) and torque about the tip (kN·m) over time (the
    store's N and N·m, in the report's units)."""
    fig = Figure(figsize=(9, 6), layout="constrained")
    ax_f, ax_t = fig.subplots(2, 1, sharex=True)
    t = ds["time"].values
    for ax, name, unit in ((ax_f, "force", "kN"), (ax_t, "torque", "kN·m")):
        v = ds[name].values / 1000.0
        for a, c in enumerate("xyz"):
            ax.plot(t, v[:, a], lw=1, label=f"{name} {c}")
        ax.plot(t, np.linalg.norm(v, axis=1), "k", lw=1.2, label=f"|{name}|")
        ax.set_ylabel(f"{name} ({unit})")
        ax.legend(loc="upper left", fontsize=10, ncol=4)
        ax.grid(alpha=0.3)
    ax_t.set_xlabel("time (s)")
    ax_f.set_title(
        f"blade force and torque about the tip — {ds.attrs.get('scenario')}, "
        f"v = {ds.attrs.get('speed')} m/s, d = {ds.attrs.get('depth')} m"
    )
    with atomic_output(path, FIGURE) as tmp:
        fig.savefig(tmp, format="png", dpi=110, metadata=png_metadata())
    return Path(path)


def animate(ds: xr.Dataset, path: str | Path, *, frames: int = 60, fps: int = 10) -> Path:
    """Write a GIF of the middle y-slice over the run, ``frames`` evenly spaced steps (>= 1)."""
    if frames < 1 or fps < 1:
        raise ValueError(f"frames and fps must be >= 1, got {frames}, {fps}")
    n = ds.sizes["time"]
    if n == 0:
        raise ValueError("cannot animate a store with no steps")
    steps = np.unique(np.linspace(0, n - 1, min(frames, n)).round().astype(int))
    vmax = _density_max(ds)
    fig = Figure(figsize=(8, 4.5), layout="constrained")
    view = _Slice(fig, ds, vmax)
    view.show(int(steps[0]))
    return write_gif(fig, lambda s: view.show(int(s)), view.artists, steps, path, fps=fps, dpi=80)


def write_gif(
    fig: Figure,
    show: Callable[[int], None],
    animated: Sequence[Artist],
    steps: Sequence[int] | np.ndarray,
    path: str | Path,
    *,
    fps: int,
    dpi: int,
) -> Path:
    """Draw ``fig`` once per step (``show(step)`` updates the ``animated`` artists, the only
    ones that change) and write the frames as a looping GIF at ``path``, marked as ours
    (:data:`dozerlab.runtime.ANIMATION`), ``fps`` frames per s.

    The rest of the figure (axes, ticks, labels, colour bars) is drawn once and each frame
    draws only ``animated`` over it (blitting): redrawing the text of every axis took ≈ 0.2 s a
    frame. Animated artists are drawn above the static ones, in the order given.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from PIL import Image

    fig.set_dpi(dpi)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    fig.set_layout_engine("none")  # fix the layout once; frames only swap data
    for artist in animated:
        artist.set_animated(True)
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)
    images = []
    for s in steps:
        show(int(s))
        canvas.restore_region(background)
        for artist in animated:
            fig.draw_artist(artist)
        # Fast octree quantisation: the frames look the same, and the default median cut took
        # ≈ 24 ms a frame, half of a comparison job's animation time.
        frame = Image.fromarray(np.asarray(canvas.buffer_rgba())[..., :3])
        images.append(frame.quantize(colors=256, method=Image.Quantize.FASTOCTREE))
    with atomic_output(path, ANIMATION) as tmp:
        # The comment marks the GIF as ours, so a later run may replace it (runtime.ANIMATION).
        images[0].save(
            tmp,
            format="GIF",
            save_all=True,
            append_images=images[1:],
            duration=int(1000 / fps),
            loop=0,
            comment=MARK,
        )
    return Path(path)


def plot_run(
    ds: xr.Dataset,
    out_dir: str | Path,
    *,
    steps: Sequence[int] | None = None,
    animation: bool = True,
    frames: int = 60,
) -> list[Path]:
    """Write the folder ``out_dir`` (:data:`FIELD_PLOTS`, built whole and moved into place):
    slices at ``steps`` (default: four spread over the run), the force plot and a GIF of
    ``frames`` frames. Returns the figures' paths."""
    out = Path(out_dir)
    n = ds.sizes["time"]
    if steps is None:
        steps = sorted({int(s) for s in np.linspace(0, max(n - 1, 0), min(4, n)).round()})
    with atomic_output(out, FIELD_PLOTS) as tmp:
        tmp.mkdir()
        paths = [plot_slice(ds, s, tmp / f"slice_{s % n:06d}.png") for s in steps]
        paths.append(plot_force(ds, tmp / "force.png"))
        if animation and n:
            paths.append(animate(ds, tmp / "fields.gif", frames=frames))
    return [out / p.name for p in paths]
