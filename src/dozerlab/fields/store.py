"""The field store: sampled fields of one run as a zarr v3 group that ``xarray.open_zarr`` opens.

Schema (docs/data.md, "The field store"):

========================================  ==============================  =====================
variable                                  dims                            unit
========================================  ==============================  =====================
``velocity``                              (time, x, y, z, component)      m/s, float32
``density``                               (time, x, y, z)                 kg/m³, float32
``force``, ``torque``                     (time, component)               N, N·m (torque about the tip)
``blade_velocity``, ``blade_position``    (time, component)               m/s, m (tip, world frame)
``time``                                  (time)                          s
========================================  ==============================  =====================

Coordinates ``x``, ``y``, ``z`` are bin centres in the blade frame (origin at the tip),
``component`` is ``["x", "y", "z"]``.

:class:`FieldStoreWriter` writes a store while a run produces it, in constant memory: it buffers
one chunk of ``chunk_steps`` steps, then writes it. Each field chunk is a zarr *shard* of inner
chunks of a few steps (8 by default): large enough that a whole-run read is not dominated by
per-chunk overhead, small enough that a batch of steps decodes little it did not ask for
(``benchmarks/field_store_read.py`` measured 1 step per inner chunk at half the read speed).
:func:`dozerlab.fields.reader.read_field` reads this layout several times faster than zarr does.
The store is built in a temporary sibling that is renamed on a successful close, so a failed run
leaves nothing behind.

Every byte is checksummed: each chunk of every array (each inner chunk of a shard) ends in its
CRC32C (zarr's ``crc32c`` codec, last in the chain), and on close the group records the SHA-256
of each array's ``zarr.json`` and of its other attributes (``metadata_sha256``).
:func:`open_store` checks all of them (:func:`dozerlab.fields.reader.check_metadata`,
:func:`~dozerlab.fields.reader.damaged_pieces`) and refuses a store without them
(:class:`~dozerlab.fields.reader.UncheckedStoreError`, see :mod:`dozerlab.fields.reader` for why).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import math
import sys
import warnings
from collections.abc import Mapping
from contextlib import ExitStack
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
import zarr
from zarr.codecs import BloscCodec, Crc32cCodec
from zarr.core import sync as zarr_sync
from zarr.storage import LocalStore, MemoryStore

from dozerlab.fields.reader import (
    DIGEST_ATTR,
    DamagedStoreError,
    check_metadata,
    damaged_pieces,
    metadata_digests,
    read_field,
    read_metadata,
)
from dozerlab.runtime import OutputKind, atomic_output

if TYPE_CHECKING:
    import xarray as xr
    from zarr.core.array_spec import ArrayConfigParams

COMPONENTS = ("x", "y", "z")
#: Dimensions of each data variable.
SCHEMA: dict[str, tuple[str, ...]] = {
    "velocity": ("time", "x", "y", "z", "component"),
    "density": ("time", "x", "y", "z"),
    "force": ("time", "component"),
    "torque": ("time", "component"),
    "blade_velocity": ("time", "component"),
    "blade_position": ("time", "component"),
}
UNITS = {
    "velocity": "m/s",
    "density": "kg/m^3",
    "force": "N",
    "torque": "N*m",
    "blade_velocity": "m/s",
    "blade_position": "m",
    "time": "s",
    "x": "m",
    "y": "m",
    "z": "m",
}
#: Attributes every store carries (values may be null where a source lacks them).
ATTRS = (
    "scenario",
    "speed",
    "depth",
    "bins",
    "bin_size",
    "dt",
    "iterations",
    "sample_every",
    "particle_count",
    "seed",
    "dozerlab_version",
    "config",
)


#: The store attribute naming the command that wrote the store (an :class:`OutputKind`'s name).
OUTPUT_ATTR = "dozerlab_output"


def store_output(attrs: dict[str, Any]) -> str:
    """The command that wrote a store of these attributes: its :data:`OUTPUT_ATTR`, or for a
    store written before that attribute, the one its attributes show (a reduced run names its
    dynamics model, an import its legacy source)."""
    if OUTPUT_ATTR in attrs:
        return str(attrs[OUTPUT_ATTR])
    if "dynamics_model" in attrs:
        return "reduce"
    return "import-legacy" if str(attrs.get("source", "")).startswith("legacy") else "simulate"


def field_store_kind(what: str, name: str) -> OutputKind:
    """The kind of a field store that command ``name`` writes: a zarr group of ours
    (``dozerlab_version`` among its attributes) that ``name`` wrote (:func:`store_output`)."""

    def recognise(path: Path) -> bool:
        meta = path / "zarr.json"
        if path.is_symlink() or not meta.is_file():
            return False
        doc = json.loads(meta.read_text())
        attrs = doc.get("attributes", {})
        return (
            doc.get("node_type") == "group"
            and "dozerlab_version" in attrs
            and store_output(attrs) == name
        )

    return OutputKind(what, recognise, name)


#: What ``simulate`` writes; only an earlier store of ``simulate`` may be replaced.
FIELD_STORE = field_store_kind("a dozerlab field store written by simulate", "simulate")
#: zarr skips chunks that hold only the fill value; written all, a missing one is damage, not a
#: run of zeros (``reader.damaged_pieces``, :func:`open_store`).
_ALL_CHUNKS: ArrayConfigParams = {"write_empty_chunks": True}
#: Steps per shard (``benchmarks/field_store_read.py`` compares 16/64/256).
DEFAULT_CHUNK_STEPS = 64
#: Steps per inner chunk of a shard.
DEFAULT_INNER_STEPS = 8


#: The data type of every array of a field store (``zarr.json`` ``data_type``).
DTYPES = {"x": "float32", "y": "float32", "z": "float32", "time": "float64"} | dict.fromkeys(
    SCHEMA, "float32"
)


def _checksummed(codec: Any) -> list[Any]:
    """An array's bytes-to-bytes codecs: ``codec`` (one, a sequence, or none) then a CRC32C."""
    codecs = list(codec) if isinstance(codec, (list, tuple)) else [codec]
    return [c for c in codecs if not isinstance(c, Crc32cCodec)] + [Crc32cCodec()]


def default_codec() -> BloscCodec:
    """The fields' compressor: Blosc LZ4 without shuffle.

    ``benchmarks/field_store_read.py`` compares codecs: on sampled fields (runs of empty bins,
    float32 values) LZ4 without shuffle both compresses better and decodes 2-4x faster than with
    byte shuffle, and Zstd decodes at a fraction of LZ4's speed.
    """
    return BloscCodec(cname="lz4", clevel=5, shuffle="noshuffle")


def settle_zarr_io(timeout_s: float = 60.0) -> None:
    """Wait until zarr's IO thread has finished the work in flight (at most ``timeout_s``).

    zarr runs a write as a coroutine on its own event-loop thread while the caller waits for it.
    A signal that ends the caller's wait (SIGTERM raising ``SystemExit``, Ctrl-C) leaves the
    coroutine writing: a temporary removed at that moment got chunk files back, or its removal
    failed on a directory filled under it (6 of 100 SIGTERMs mid-write, two cores busy). Call
    this before removing a store that an exception interrupted.
    """
    loop = zarr_sync.loop[0]
    if loop is None or loop.is_closed():
        return

    async def in_flight() -> None:
        me = asyncio.current_task()
        await asyncio.gather(
            *(t for t in asyncio.all_tasks() if t is not me), return_exceptions=True
        )

    concurrent.futures.wait([asyncio.run_coroutine_threadsafe(in_flight(), loop)], timeout_s)


class FieldStoreWriter:
    """Write a field store step by step in constant memory (one buffered chunk).

    Use as a context manager; the store appears at ``path`` only when the block exits without
    an exception.

    Args:
        path: the ``.zarr`` directory to create (an existing field store there is replaced;
            anything else is refused, :class:`~dozerlab.runtime.OutputExistsError`).
        x, y, z: bin-centre coordinates in the blade frame, m; shapes (Nx,), (Ny,), (Nz,).
        attrs: store attributes (docs/data.md); must be JSON-serialisable.
        kind: the command's kind of store (default: ``simulate``'s, :data:`FIELD_STORE`); its
            name is recorded as the attribute :data:`OUTPUT_ATTR`.
        chunk_steps: time steps per shard (>= 1).
        codec: the fields' compressor (default :func:`default_codec`; a sequence of codecs, or
            ``()`` for none); every array's chain ends in a CRC32C whatever it is.
        inner_steps: time steps per inner chunk of a shard (must divide chunk_steps; default:
            ``gcd(chunk_steps, DEFAULT_INNER_STEPS)``).
        steps: the time steps the caller will append, if known (>= 0): the arrays are made that
            long at once rather than grown a chunk at a time (a resize of every array a chunk
            was a third of a reduced run's writing); a store closed shorter is cut to what was
            appended, one appended longer grows as without it.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        x: np.ndarray,
        y: np.ndarray,
        z: np.ndarray,
        attrs: Mapping[str, Any],
        kind: OutputKind = FIELD_STORE,
        chunk_steps: int = DEFAULT_CHUNK_STEPS,
        codec: Any = None,
        inner_steps: int | None = None,
        steps: int | None = None,
    ) -> None:
        if steps is not None and steps < 0:
            raise ValueError(f"steps must be >= 0, got {steps}")
        if chunk_steps < 1:
            raise ValueError(f"chunk_steps must be >= 1, got {chunk_steps}")
        if inner_steps is None:
            inner_steps = math.gcd(chunk_steps, DEFAULT_INNER_STEPS)
        if not 1 <= inner_steps <= chunk_steps or chunk_steps % inner_steps:
            raise ValueError(
                f"inner_steps must divide chunk_steps={chunk_steps}, got {inner_steps}"
            )
        self.coords = {}
        for name, c in (("x", x), ("y", y), ("z", z)):
            c = np.ascontiguousarray(c, dtype=np.float32)
            if c.ndim != 1 or c.size < 1:
                raise ValueError(
                    f"coordinate {name} must be a non-empty 1-D array, got shape {c.shape}"
                )
            self.coords[name] = c
        try:
            self.attrs = json.loads(json.dumps(dict(attrs), allow_nan=False))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"store attrs must be JSON-serialisable without NaN: {exc}") from exc
        self.kind = kind
        self.attrs[OUTPUT_ATTR] = kind.name
        self.path = Path(path)
        self.chunk_steps = chunk_steps
        self.inner_steps = inner_steps
        self.codec = codec if codec is not None else default_codec()
        self.grid = (self.coords["x"].size, self.coords["y"].size, self.coords["z"].size)
        self.steps = 0
        self._length = steps or 0  # the arrays' length along time
        self._fill = 0
        self._stack: ExitStack | None = None
        self._arrays: dict[str, zarr.Array] = {}
        self._buf: dict[str, np.ndarray] = {}

    def _shape(self, name: str) -> tuple[int, ...]:
        return {"velocity": (*self.grid, 3), "density": self.grid}.get(name, (3,))

    def __enter__(self) -> FieldStoreWriter:
        self._stack = ExitStack()
        tmp = self._stack.enter_context(atomic_output(self.path, self.kind))
        try:
            self._create(tmp)
        except BaseException:
            settle_zarr_io()
            self._stack.__exit__(*sys.exc_info())
            raise
        return self

    def _create(self, tmp: Path) -> None:
        # Every node's metadata is made in memory, then written in one batch: made one by one
        # in the directory, with each array's units set after it, the empty store took 54-98 ms
        # (a wait on zarr's IO thread a file), up to a tenth of a reduced run's loop
        # (BENCHMARKS.md, "A store's files written in one batch").
        layout = zarr.open_group(MemoryStore(), mode="w", zarr_format=3, attributes=self.attrs)
        for name, c in self.coords.items():
            layout.create_array(
                name,
                shape=c.shape,
                dtype="f4",
                dimension_names=(name,),
                compressors=_checksummed(()),
                attributes={"units": UNITS[name], "long_name": f"bin centre {name}, blade frame"},
            )
        layout.create_array(
            "component",
            shape=(3,),
            dtype=str,
            dimension_names=("component",),
            compressors=_checksummed(()),
        )
        n = self.chunk_steps
        layout.create_array(
            "time",
            shape=(self._length,),
            chunks=(n,),
            dtype="f8",
            dimension_names=("time",),
            fill_value=0.0,
            compressors=_checksummed(()),
            attributes={"units": UNITS["time"]},
        )
        self._buf["time"] = np.zeros(n, dtype=np.float64)
        for name, dims in SCHEMA.items():
            shape = self._shape(name)
            field = name in ("velocity", "density")
            layout.create_array(
                name,
                shape=(self._length, *shape),
                shards=(n, *shape) if field else None,
                chunks=(self.inner_steps, *shape) if field else (n, *shape),
                dtype="f4",
                dimension_names=dims,
                fill_value=0.0,
                compressors=_checksummed(self.codec if field else ()),
                attributes={"units": UNITS[name]},
            )
            self._buf[name] = np.zeros((n, *shape), dtype=np.float32)
        nodes = {"": layout.metadata} | {k: a.metadata for k, a in layout.arrays()}
        made = dict(zarr.create_hierarchy(store=LocalStore(tmp), nodes=nodes))
        group = made.pop("")
        assert isinstance(group, zarr.Group)
        # the runtime config is not metadata: it is set again on the arrays as written
        arrays = {
            k: a.with_config(_ALL_CHUNKS) for k, a in made.items() if isinstance(a, zarr.Array)
        }
        self._arrays = {k: arrays[k] for k in ("time", *SCHEMA)}
        _write_all(
            [(arrays[k], c) for k, c in self.coords.items()]
            + [(arrays["component"], np.array(COMPONENTS))]
        )
        self._group = group
        self._tmp = tmp

    def append(
        self,
        time: float,
        velocity: np.ndarray,
        density: np.ndarray,
        force: np.ndarray,
        torque: np.ndarray,
        blade_velocity: np.ndarray,
        blade_position: np.ndarray,
    ) -> None:
        """Add one sampled step.

        Args:
            time: simulated time, s.
            velocity: bin velocities (Nx, Ny, Nz, 3), m/s.
            density: bin densities (Nx, Ny, Nz), kg/m³.
            force, torque: on the blade, (3,) N and N·m about the tip.
            blade_velocity, blade_position: of the tip, (3,) m/s and m.
        """
        if self._stack is None:
            raise RuntimeError("FieldStoreWriter.append called outside its `with` block")
        values = {
            "velocity": velocity,
            "density": density,
            "force": force,
            "torque": torque,
            "blade_velocity": blade_velocity,
            "blade_position": blade_position,
        }
        i = self._fill
        for name, v in values.items():
            v = np.asarray(v)
            if v.shape != self._shape(name):
                raise ValueError(f"{name} must have shape {self._shape(name)}, got {v.shape}")
            self._buf[name][i] = v
        self._buf["time"][i] = time
        self._fill += 1
        if self._fill == self.chunk_steps:
            self._flush()

    def update_attrs(self, **attrs: Any) -> None:
        """Add or replace store attributes before the store is complete, such as figures known
        only at the end of a run (``wall_time_s``); values must be JSON-serialisable."""
        if self._stack is None:
            raise RuntimeError("FieldStoreWriter.update_attrs called outside its `with` block")
        try:
            attrs = json.loads(json.dumps(attrs, allow_nan=False))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"store attrs must be JSON-serialisable without NaN: {exc}") from exc
        self.attrs.update(attrs)
        self._group.attrs.update(attrs)

    def _flush(self) -> None:
        k = self._fill
        if k == 0:
            return
        start, stop = self.steps, self.steps + k
        if stop > self._length:
            for a in self._arrays.values():
                a.resize((stop, *a.shape[1:]))
        _write_all([(a, self._buf[name][:k]) for name, a in self._arrays.items()], start)
        self._length = max(self._length, stop)
        self.steps = stop
        self._fill = 0

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> bool:
        stack, self._stack = self._stack, None
        assert stack is not None
        if exc_type is not None:
            settle_zarr_io()
        if exc_type is None:
            try:
                self._flush()
                if self._length > self.steps:  # fewer steps than announced: no zero rows
                    for a in self._arrays.values():
                        a.resize((self.steps, *a.shape[1:]))
                    self._length = self.steps
                names = [*self.coords, "component", *self._arrays]
                self._group.attrs[DIGEST_ATTR] = metadata_digests(self._tmp, names)
                with warnings.catch_warnings():
                    # zarr notes that consolidated metadata is outside the v3 spec; xarray reads it.
                    warnings.simplefilter("ignore")
                    zarr.consolidate_metadata(self._group.store)
            except BaseException:
                # a signal in the closing write leaves it running, as one in the block does
                settle_zarr_io()
                stack.__exit__(*sys.exc_info())
                raise
        return bool(stack.__exit__(exc_type, exc, tb))


def _write_all(parts: list[tuple[Any, np.ndarray]], start: int | None = None) -> None:
    """Write each array's values in one batch on zarr's IO thread (one wait, not one per
    array): all of each array, or from ``start`` along its first axis when given."""

    async def batch() -> None:
        await asyncio.gather(
            *(
                a.async_array.setitem(
                    slice(None) if start is None else slice(start, start + len(v)), v
                )
                for a, v in parts
            )
        )

    zarr_sync.sync(batch())


def write_store(
    path: str | Path,
    *,
    attrs: Mapping[str, Any],
    kind: OutputKind = FIELD_STORE,
    chunk_steps: int = DEFAULT_CHUNK_STEPS,
    codec: Any = None,
    inner_steps: int | None = None,
    **arrays: np.ndarray,
) -> Path:
    """Write whole arrays as a field store; returns ``path``.

    ``arrays`` are the coordinates ``x``, ``y``, ``z`` and ``time`` (T,) and the variables of
    :data:`SCHEMA`, each by its name, shapes as in :meth:`FieldStoreWriter.append` with a
    leading (T,) axis; ``attrs`` and the writer's options as in :class:`FieldStoreWriter`.
    """
    names = ("x", "y", "z", "time", *SCHEMA)
    if set(arrays) != set(names):
        raise ValueError(
            f"write_store needs the arrays {list(names)}; missing "
            f"{[k for k in names if k not in arrays]}, unknown {sorted(set(arrays) - set(names))}"
        )
    time = np.asarray(arrays["time"])
    if time.ndim != 1:
        raise ValueError(f"time must be 1-D, got shape {time.shape}")
    for name in SCHEMA:
        if len(arrays[name]) != time.size:
            raise ValueError(f"{name} has {len(arrays[name])} steps but time has {time.size}")
    coords: dict[str, Any] = {k: arrays[k] for k in ("x", "y", "z")}
    options: dict[str, Any] = {
        "kind": kind,
        "chunk_steps": chunk_steps,
        "codec": codec,
        "inner_steps": inner_steps,
    }
    with FieldStoreWriter(path, attrs=attrs, **coords, **options, steps=time.size) as w:
        for i in range(time.size):
            w.append(float(time[i]), *(arrays[name][i] for name in SCHEMA))
    return Path(path)


def open_store(path: str | Path) -> xr.Dataset:
    """Open a field store lazily and check it against the schema and for damage.

    Raises ``ValueError`` naming every missing variable, coordinate or attribute and every
    variable with the wrong dimensions or data type, and
    :class:`~dozerlab.fields.reader.DamagedStoreError` naming the file, or the array and the
    piece, when metadata or a chunk fails its checksum, when a chunk its metadata implies is
    missing, when ``time`` is not finite and strictly increasing, or when a force, torque or
    blade series holds NaN/inf; :class:`~dozerlab.fields.reader.UncheckedStoreError` for a store
    written without checksums. Every chunk's encoded bytes are read once for their CRC32C
    (decoding nothing); the fields' values are checked for NaN/inf as
    :func:`~dozerlab.fields.reader.read_field` reads them.
    """
    import xarray as xr  # here: 0.4 s of importing xarray and pandas, which writers never need

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"field store not found: {path}")
    group = read_metadata(path / "zarr.json") if (path / "zarr.json").is_file() else {}
    # A store with checksums is checked before xarray reads its coordinates (zarr would raise
    # a bare checksum error); one without is refused after the schema, which names what it is.
    checked = DIGEST_ATTR in (group.get("attributes") or {})
    if checked:
        _check_bytes(path)
    try:
        ds = xr.open_zarr(path)
    except Exception as exc:  # zarr/xarray raise several kinds for a non-store directory
        raise ValueError(f"{path} is not a readable zarr field store: {exc}") from exc
    problems = []
    for name, dims in SCHEMA.items():
        if name not in ds.variables:
            problems.append(f"missing variable '{name}' {dims}")
        elif ds[name].dims != dims:
            problems.append(f"variable '{name}' has dims {ds[name].dims}, expected {dims}")
    for name in ("time", "x", "y", "z", "component"):
        if name not in ds.coords:
            problems.append(f"missing coordinate '{name}'")
    if "component" in ds.coords and [str(c) for c in ds["component"].values] != list(COMPONENTS):
        problems.append(f"coordinate 'component' must be {list(COMPONENTS)}")
    missing_attrs = [a for a in ATTRS if a not in ds.attrs]
    if missing_attrs:
        problems.append(f"missing attributes {missing_attrs}")
    if problems:
        raise ValueError(f"{path} is not a valid field store: " + "; ".join(problems))
    if not checked:
        check_metadata(path)  # raises UncheckedStoreError
    _check_series(path, ds)
    return ds


def _check_bytes(path: Path) -> None:
    """Refuse a changed data type, changed metadata, lost or corrupt chunks (naming each)."""
    for name, dtype in DTYPES.items():
        file = path / name / "zarr.json"
        if file.is_file() and (found := read_metadata(file).get("data_type")) != dtype:
            raise DamagedStoreError(
                f"{file} gives data type {found!r}, a field store's '{name}' is {dtype!r} (the "
                "metadata was edited or damaged)"
            )
    damaged = [
        f"array '{name}': {', '.join(pieces)}"
        for name in check_metadata(path)
        if (pieces := damaged_pieces(path, name))
    ]
    if damaged:
        raise DamagedStoreError(
            f"{path} is damaged (lost or changed files, or a copy cut short; re-run the job that "
            "wrote it, or copy it again): " + "; ".join(damaged)
        )


def verify_store(path: str | Path, window: int = 256) -> None:
    """Check a whole field store (``dozerlab verify``): :func:`open_store`'s checks, then every
    step of the fields decoded and checked for NaN/inf, ``window`` steps at a time (constant
    memory); raises as they do."""
    ds = open_store(path)
    steps = ds.sizes["time"]
    for name in ("velocity", "density"):
        for start in range(0, steps, window):
            read_field(path, name, start, start + window)


def _check_series(path: Path, ds: xr.Dataset) -> None:
    """Refuse a time axis that is not finite and strictly increasing, NaN/inf in the series."""
    t = np.asarray(ds["time"].values)
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise DamagedStoreError(f"{path}: array 'time' holds NaN/inf, first at step {bad[0]}")
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        i = int(back[0])
        raise DamagedStoreError(
            f"{path}: array 'time' is not strictly increasing: step {i + 1} at {t[i + 1]} s "
            f"follows {t[i]} s"
        )
    for name in ("force", "torque", "blade_velocity", "blade_position"):
        values = np.asarray(ds[name].values)
        where = np.argwhere(~np.isfinite(values))
        if where.size:
            raise DamagedStoreError(
                f"{path}: array '{name}' holds {len(where)} NaN/inf value(s), first at step {where[0][0]}"
            )


def store_config(ds: xr.Dataset) -> dict[str, Any]:
    """The run's configuration recorded in a store's ``config`` attribute ({} when absent)."""
    text = ds.attrs.get("config")
    if not text:
        return {}
    return json.loads(text) if isinstance(text, str) else dict(text)
