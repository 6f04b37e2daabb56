"""Field plots and the plot-fields / legacy commands."""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path

import numpy as np
from matplotlib.artist import Artist
from matplotlib.figure import Figure
from PIL import Image, ImageSequence

from dozerlab.cli import main
from dozerlab.fields.plots import write_gif
from dozerlab.fields.store import write_store
from dozerlab.runtime import FOLDER_MARK


def test_plot_fields_command_writes_slices_force_and_gif(tmp_path, store_arrays):
    store = write_store(tmp_path / "f.zarr", **store_arrays)
    assert (
        main(
            [
                "plot-fields",
                str(store),
                "--out",
                str(tmp_path / "plots"),
                "--steps",
                "0",
                "69",
                "--frames",
                "12",
            ]
        )
        == 0
    )
    names = sorted(p.name for p in (tmp_path / "plots").iterdir())
    assert names == [FOLDER_MARK, "fields.gif", "force.png", "slice_000000.png", "slice_000069.png"]
    with Image.open(tmp_path / "plots" / "fields.gif") as gif:
        assert gif.n_frames == 12
    assert main(["plot-fields", str(store), "--out", str(tmp_path / "p2"), "--steps", "70"]) == 2


def test_legacy_commands_round_trip(tmp_path, store_arrays):
    a = dict(store_arrays)
    a["attrs"] = a["attrs"] | {"bin_size": [0.1, 0.2, 0.1]}
    store = write_store(tmp_path / "f.zarr", **a)
    assert main(["export-legacy", str(store), str(tmp_path / "f.bin")]) == 0
    assert (
        main(
            [
                "import-legacy",
                str(tmp_path / "f.bin"),
                str(tmp_path / "g.zarr"),
                "--lower",
                "0",
                "-0.3",
                "-0.1",
            ]
        )
        == 0
    )
    import xarray as xr

    ds = xr.open_zarr(tmp_path / "g.zarr")
    np.testing.assert_array_equal(ds["velocity"].values, a["velocity"])
    np.testing.assert_allclose(ds["y"].values, [-0.2, 0.0, 0.2], atol=1e-7)
    (tmp_path / "bad.bin").write_bytes(b"\0" * 30)
    assert main(["import-legacy", str(tmp_path / "bad.bin"), str(tmp_path / "h.zarr")]) == 2
    assert not (tmp_path / "h.zarr").exists()


def _stepped_figure() -> tuple[Figure, Callable[[int], None], list[Artist]]:
    """A figure whose image and title show the step; returns it, its show and its artists."""
    fig = Figure(figsize=(3, 2))
    ax = fig.add_subplot()
    image = ax.imshow(np.zeros((4, 5)), vmin=0.0, vmax=3.0)
    ax.set_xlabel("x (m)")

    def show(step: int) -> None:
        image.set_data(np.arange(20.0).reshape(4, 5) % (step + 1))
        ax.set_title(f"step {step}")

    show(0)
    return fig, show, [image, ax.title]


def _gif_frames(path: Path) -> list[np.ndarray]:
    # the iterator seeks one image: convert each frame while it is current
    return [
        np.asarray(f.convert("RGB"), dtype=int) for f in ImageSequence.Iterator(Image.open(path))
    ]


def test_gif_frames_drawn_over_the_static_figure_match_full_draws(tmp_path):
    fig, show, animated = _stepped_figure()
    write_gif(fig, show, animated, [0, 1, 2], tmp_path / "blit.gif", fps=5, dpi=50)
    full = []
    for step in range(3):
        ref, ref_show, _ = _stepped_figure()
        ref_show(step)
        buf = io.BytesIO()
        ref.savefig(buf, format="rgba", dpi=50)
        full.append(Image.frombuffer("RGBA", (150, 100), buf.getvalue(), "raw", "RGBA", 0, 1))
    rgb = [im.convert("RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE) for im in full]
    rgb[0].save(tmp_path / "full.gif", format="GIF", save_all=True, append_images=rgb[1:])
    # Animated artists are drawn above the static ones: the image covers the axes' frame, a
    # band of 2 pixels around its edges; everything else (the title too) is as drawn in full.
    x0, y0, x1, y1 = np.round(fig.axes[0].get_window_extent().extents).astype(int)
    rows, cols = np.mgrid[0:100, 0:150]
    frame = (np.minimum(abs(cols - x0), abs(cols - x1)) <= 2) | (
        np.minimum(abs(rows - (100 - y0)), abs(rows - (100 - y1))) <= 2
    )
    got, want = _gif_frames(tmp_path / "blit.gif"), _gif_frames(tmp_path / "full.gif")
    assert len(got) == len(want) == 3
    for g, w in zip(got, want, strict=True):
        assert not np.abs(g - w).sum(axis=-1)[~frame].any()
