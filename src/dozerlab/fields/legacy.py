"""The thesis's raw binary field format (docs/data.md): import to and export from stores.

Layout, every word 4 bytes little-endian::

    header     n_bins   3 × int32      (Nx, Ny, Nz)
               bin_size 3 × float32    m
    each step  time 1, force 3, torque 3, blade velocity 3      float32 (s, N, N·m, m/s)
               each bin: velocity 3, density 1                  float32 (m/s, kg/m³)

so a file has ``6 + n_steps·(10 + 4·Nx·Ny·Nz)`` words. Bins are in C order of (x, y, z): x-major,
z fastest — the order ``velocity[t].reshape(-1, 3)`` gives.

The format has no bin coordinates and no blade position. Import places the bins in the blade
frame as x ∈ [0, Nx·lx] in front of the tip, y centred, z from the volume's bottom edge upwards
unless ``lower`` gives the volume's minimum corner; it reconstructs ``blade_position`` by
integrating the blade velocity over the steps from zero at the first step (attribute
``blade_position_origin`` says so). Export drops ``blade_position``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from dozerlab import __version__
from dozerlab.fields.store import (
    ATTRS,
    DEFAULT_CHUNK_STEPS,
    FieldStoreWriter,
    field_store_kind,
    open_store,
)
from dozerlab.runtime import OutputKind, atomic_output, job_outputs

HEADER_BYTES = 24
_HEADER = np.dtype([("bins", "<i4", 3), ("bin_size", "<f4", 3)])


def _record_dtype(bins: Sequence[int]) -> np.dtype:
    return np.dtype(
        [
            ("time", "<f4"),
            ("force", "<f4", 3),
            ("torque", "<f4", 3),
            ("blade_velocity", "<f4", 3),
            ("cells", "<f4", (*bins, 4)),
        ]
    )


def read_header(path: str | Path) -> tuple[tuple[int, int, int], tuple[float, float, float], int]:
    """Check a legacy file's header and length; return (bins, bin_size in m, step count).

    Raises ``ValueError`` saying at which byte offset / step the file is inconsistent or truncated.
    """
    path = Path(path)
    size = path.stat().st_size
    if size < HEADER_BYTES:
        raise ValueError(f"{path}: truncated header: {size} bytes, the header needs {HEADER_BYTES}")
    header = np.fromfile(path, dtype=_HEADER, count=1)[0]
    nx, ny, nz = (int(n) for n in header["bins"])
    bins = (nx, ny, nz)
    if min(bins) < 1 or max(bins) > 4096:
        raise ValueError(
            f"{path}: bin counts {bins} at byte offset 0 are outside 1..4096 (not a legacy field file?)"
        )
    sx, sy, sz = (float(s) for s in header["bin_size"])
    bin_size = (sx, sy, sz)
    if not all(np.isfinite(s) and 0 < s < 1e3 for s in bin_size):
        raise ValueError(f"{path}: bin sizes {bin_size} at byte offset 12 are not in (0, 1000) m")
    record = _record_dtype(bins).itemsize
    steps, rest = divmod(size - HEADER_BYTES, record)
    if rest:
        offset = HEADER_BYTES + steps * record
        raise ValueError(
            f"{path}: truncated at step {steps}: the record starting at byte offset {offset} needs "
            f"{record} bytes but only {rest} remain (header says {bins} bins)"
        )
    return bins, bin_size, steps


def _is_legacy(path: Path) -> bool:
    """A file whose header and length are consistent legacy field data (:func:`read_header`)."""
    if not path.is_file():
        return False
    try:
        read_header(path)
    except ValueError:
        return False
    return True


#: What ``export-legacy --overwrite`` replaces: the format has no room for a mark of ours, so a
#: file whose header and length are consistent, ours or a user's; without ``--overwrite``,
#: :data:`NEW_LEGACY_FILE`.
LEGACY_FILE = OutputKind("a legacy binary field file", _is_legacy)
#: What ``export-legacy`` replaces without ``--overwrite``: nothing.
NEW_LEGACY_FILE = OutputKind(
    "known to be ours (the legacy format has no room for a mark; --overwrite replaces a legacy "
    "binary field file)",
    lambda path: False,
)
#: What ``import-legacy`` writes; only an earlier import may be replaced.
IMPORTED_STORE = field_store_kind(
    "a dozerlab field store written by import-legacy", "import-legacy"
)


def import_legacy(
    src: str | Path,
    out: str | Path,
    *,
    lower: Sequence[float] | None = None,
    chunk_steps: int = DEFAULT_CHUNK_STEPS,
) -> Path:
    """Convert a legacy binary file to a field store at ``out`` (nothing is left on failure).

    ``lower`` (3,) is the sampling volume's minimum corner relative to the tip, m (default:
    x from 0, y centred, z from 0 at the volume's bottom).
    """
    with job_outputs(("OUT", out, IMPORTED_STORE)):
        return _import(Path(src), out, lower, chunk_steps)


def _import(src: Path, out: str | Path, lower: Sequence[float] | None, chunk_steps: int) -> Path:
    bins, bin_size, steps = read_header(src)
    size = np.asarray(bin_size, dtype=np.float64)
    n = np.asarray(bins)
    lo = (
        np.array([0.0, -n[1] * size[1] / 2, 0.0])
        if lower is None
        else np.asarray(lower, dtype=np.float64)
    )
    if lo.shape != (3,):
        raise ValueError(f"lower must be three lengths (x, y, z) in m, got {lower}")
    x, y, z = (lo[a] + (np.arange(n[a]) + 0.5) * size[a] for a in range(3))
    attrs = dict.fromkeys(ATTRS) | {
        "scenario": "legacy",
        "bins": list(bins),
        "bin_size": list(bin_size),
        "dozerlab_version": __version__,
        "config": json.dumps({}),
        "source": f"legacy binary {src.name}",
        "blade_position_origin": "integrated from blade_velocity; zero at the first step",
    }
    if steps == 0:
        raise ValueError(
            f"{src}: the file holds a header ({bins} bins) but no steps; nothing to import"
        )
    records = np.memmap(
        src, dtype=_record_dtype(bins), mode="r", offset=HEADER_BYTES, shape=(steps,)
    )
    position = np.zeros(3)
    last_time = -np.inf
    with FieldStoreWriter(
        out, x=x, y=y, z=z, attrs=attrs, kind=IMPORTED_STORE, chunk_steps=chunk_steps
    ) as w:
        for i in tqdm(range(steps), desc=f"import {src.name}", unit="step", disable=None):
            rec = records[i]
            t = float(rec["time"])
            offset = HEADER_BYTES + i * records.dtype.itemsize
            if not np.isfinite(t) or t <= last_time:
                raise ValueError(
                    f"{src}: inconsistent time {t} at step {i} (byte offset {offset}): times must be finite and strictly increasing"
                )
            _check_record(src, rec, i, offset)
            if i:
                position = position + records[i - 1]["blade_velocity"] * (t - last_time)
            last_time = t
            cells = rec["cells"]
            w.append(
                t,
                cells[..., :3],
                cells[..., 3],
                rec["force"],
                rec["torque"],
                rec["blade_velocity"],
                position,
            )
    return Path(out)


def _check_record(src: Path, rec: np.void, step: int, offset: int) -> None:
    """Refuse NaN/inf in a step's record, naming the field, the bin and the byte offset."""
    for name in ("force", "torque", "blade_velocity", "cells"):
        bad = np.argwhere(~np.isfinite(rec[name]))
        if bad.size:
            where = f" at bin {tuple(int(i) for i in bad[0][:3])}" if name == "cells" else ""
            raise ValueError(
                f"{src}: step {step} (record at byte offset {offset}) has NaN/inf in {name}{where}; "
                "damaged data is not imported"
            )


def export_legacy(store: str | Path, out: str | Path, *, overwrite: bool = False) -> Path:
    """Write a field store as a legacy binary file (``blade_position`` is not part of the format).

    The format has no room for a mark of ours, so an existing ``out`` is refused, whoever wrote
    it; ``overwrite`` replaces one that is a legacy binary field file (:data:`LEGACY_FILE`)."""
    kind = LEGACY_FILE if overwrite else NEW_LEGACY_FILE
    with job_outputs(("OUT", out, kind)):
        return _export(store, out, kind)


def _export(store: str | Path, out: str | Path, kind: OutputKind) -> Path:
    ds = open_store(store)
    nx, ny, nz = (ds.sizes[d] for d in ("x", "y", "z"))
    bin_size = ds.attrs.get("bin_size") or [
        float(np.diff(ds[d].values[:2])[0]) if ds.sizes[d] > 1 else 0.0 for d in "xyz"
    ]
    if len(bin_size) != 3 or min(bin_size) <= 0:
        raise ValueError(f"{store}: cannot export: bin_size {bin_size} must be three lengths > 0")
    steps = ds.sizes["time"]
    header = np.array([((nx, ny, nz), bin_size)], dtype=_HEADER)
    record = _record_dtype((nx, ny, nz))
    block = int(
        ds["velocity"].encoding.get("preferred_chunks", {}).get("time", DEFAULT_CHUNK_STEPS)
    )
    with atomic_output(out, kind) as tmp, open(tmp, "wb") as f:
        f.write(header.tobytes())
        for start in tqdm(
            range(0, steps, block), desc=f"export {Path(store).name}", unit="chunk", disable=None
        ):
            part = ds.isel(time=slice(start, start + block))
            rec = np.zeros(part.sizes["time"], dtype=record)
            rec["time"] = part["time"].values
            for name in ("force", "torque", "blade_velocity"):
                rec[name] = part[name].values
            rec["cells"][..., :3] = part["velocity"].values
            rec["cells"][..., 3] = part["density"].values
            f.write(rec.tobytes())
    return Path(out)
