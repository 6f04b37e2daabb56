"""Fast whole-array and time-window reads of a field store's sharded fields.

zarr-python 3 reads a field store correctly but tops out near 1.2 GB/s on two cores whatever the
codec (``benchmarks/field_store_read.py``): its async pipeline copies each inner chunk several
times. The stores this package writes have one layout — shards along time only, inner chunks of a
few whole steps, ``bytes`` then optionally ``blosc``, a CRC-checked index at the shard's end — and
for that layout :func:`read_field` reads the shard files itself and has Blosc decode every inner
chunk straight into the output array, on a thread per core (Blosc releases the GIL).

Any other layout (a store rewritten by another tool, a non-sharded array) is read through zarr,
so the result is always the same array ``zarr.open_array(path / name)[start:stop]`` returns.

A store never silently reads as zeros: the writer writes every chunk, even an empty one, so a
chunk file or an inner chunk that the metadata implies but the store lacks is damage
(:func:`missing_pieces`), and :func:`read_field` refuses it, as it refuses NaN and inf.
"""

from __future__ import annotations

import functools
import itertools
import json
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import google_crc32c
import numpy as np
import zarr
from numcodecs import blosc

from dozerlab.runtime import thread_budget

#: Index entry of an inner chunk that was never written (zarr v3 sharding spec): read as fill.
_MISSING = np.uint64(2**64 - 1)


@dataclass(frozen=True)
class _Layout:
    """What the fast path needs from an array's ``zarr.json``."""

    shape: tuple[int, ...]
    shard_steps: int
    inner_steps: int
    compressed: bool
    fill_value: float


def _layout(meta: dict[str, Any]) -> _Layout | None:
    """The fast-path layout of an array, or None when it is anything else."""
    try:
        shape = tuple(int(n) for n in meta["shape"])
        shard = meta["chunk_grid"]["configuration"]["chunk_shape"]
        keys = meta["chunk_key_encoding"]
        (codec,) = meta["codecs"]
        conf = codec["configuration"]
        inner = conf["chunk_shape"]
        names = [c["name"] for c in conf["codecs"]]
        index = [c["name"] for c in conf["index_codecs"]]
        ok = (
            meta.get("zarr_format") == 3
            and meta["data_type"] == "float32"
            and meta["chunk_grid"]["name"] == "regular"
            and keys["name"] == "default"
            and keys.get("configuration", {}).get("separator", "/") == "/"
            and codec["name"] == "sharding_indexed"
            and list(shard[1:]) == list(shape[1:])
            and list(inner[1:]) == list(shape[1:])
            and shard[0] % inner[0] == 0
            and names in (["bytes"], ["bytes", "blosc"])
            and conf["codecs"][0].get("configuration", {}).get("endian", "little") == "little"
            and index == ["bytes", "crc32c"]
            and conf["index_codecs"][0].get("configuration", {}).get("endian", "little") == "little"
            and conf.get("index_location", "end") == "end"
        )
    except (KeyError, TypeError, ValueError):
        return None
    if not ok:
        return None
    return _Layout(
        shape, int(shard[0]), int(inner[0]), names[-1] == "blosc", float(meta["fill_value"])
    )


class DamagedStoreError(ValueError):
    """A store whose files do not hold what its metadata says (a missing chunk, NaN, …)."""


def _chunk_key(meta: dict[str, Any], idx: tuple[int, ...]) -> str:
    """The store key (relative to the array) of chunk ``idx`` under its key encoding."""
    enc = meta["chunk_key_encoding"]
    if enc["name"] == "default":
        sep = enc.get("configuration", {}).get("separator", "/")
        return sep.join(["c", *map(str, idx)])
    sep = enc.get("configuration", {}).get("separator", ".")
    return sep.join(map(str, idx)) or "0"


def missing_pieces(path: str | Path, name: str) -> list[str]:
    """Chunks of array ``name`` that its metadata implies but the store at ``path`` lacks.

    Every chunk of the array's shape must have its file; in a sharded field of this package's
    layout every inner chunk must be in its shard's index too. Returns readable descriptions
    (``"chunk c/1/0/0/0/0 (steps 64-127)"``); empty for a whole array.
    """
    array_dir = Path(path) / name
    meta = json.loads((array_dir / "zarr.json").read_text())
    shape = [int(n) for n in meta["shape"]]
    grid = [int(n) for n in meta["chunk_grid"]["configuration"]["chunk_shape"]]
    lay = _layout(meta)
    missing = []
    for idx in itertools.product(*(range(-(-s // c)) for s, c in zip(shape, grid, strict=True))):
        key = _chunk_key(meta, idx)
        steps = (
            f" (steps {idx[0] * grid[0]}-{min(shape[0], (idx[0] + 1) * grid[0]) - 1})"
            if idx
            else ""
        )
        file = array_dir / key
        if not file.is_file():
            missing.append(f"chunk {key}{steps}")
            continue
        if lay is None:
            continue
        with open(file, "rb") as f:
            index, _ = _read_index(f, file, lay.shard_steps // lay.inner_steps)
        s0 = idx[0] * lay.shard_steps
        for k in np.flatnonzero(index[:, 0] == _MISSING):
            a = s0 + int(k) * lay.inner_steps
            if a < shape[0]:
                b = min(shape[0], a + lay.inner_steps) - 1
                missing.append(f"inner chunk {k} of shard {key} (steps {a}-{b})")
    return missing


def _check_finite(values: np.ndarray, where: str, first_step: int) -> None:
    """Refuse NaN/inf. A float32 sum is a cheap test (SIMD, no temporary); only when it is not
    finite, which a NaN, an inf or an overflow makes it, is each value looked at."""
    if values.size and not np.isfinite(np.add.reduce(values, axis=None)):
        bad = np.argwhere(~np.isfinite(values))
        if bad.size:
            raise DamagedStoreError(
                f"{where}: {len(bad)} NaN/inf value(s), the first at step {first_step + bad[0][0]}"
            )


def _decode(src: memoryview, dest: np.ndarray, compressed: bool, where: str) -> None:
    """Decode one inner chunk into ``dest`` (C-contiguous, exactly its size)."""
    if compressed:
        # Blosc header: bytes 4-8 hold the decoded size (little-endian uint32).
        nbytes = int.from_bytes(src[4:8], "little") if len(src) >= 16 else -1
        if nbytes != dest.nbytes:
            raise ValueError(
                f"{where}: inner chunk decodes to {nbytes} bytes, expected {dest.nbytes}"
            )
        blosc.decompress(src, dest)
    else:
        if len(src) != dest.nbytes:
            raise ValueError(f"{where}: inner chunk holds {len(src)} bytes, expected {dest.nbytes}")
        dest.reshape(-1).view(np.uint8)[:] = np.frombuffer(src, dtype=np.uint8)


def _read_index(f: Any, file: Path, n_inner: int) -> tuple[np.ndarray, int]:
    """A shard's (n_inner, 2) index of (offset, nbytes), checked, and where its data end."""
    size = os.fstat(f.fileno()).st_size
    index_bytes = 16 * n_inner
    if size < index_bytes + 4:
        raise ValueError(f"{file}: shard of {size} bytes is shorter than its index")
    raw = os.pread(f.fileno(), index_bytes + 4, size - index_bytes - 4)
    if google_crc32c.value(raw[:-4]) != int.from_bytes(raw[-4:], "little"):
        raise ValueError(f"{file}: shard index fails its CRC32C check")
    return np.frombuffer(raw, dtype="<u8", count=2 * n_inner).reshape(
        n_inner, 2
    ), size - index_bytes - 4


class _Task:
    """Read and decode inner chunks ``first … last`` of one shard into the output window.

    Each task reads its chunks' bytes with one ``readinto`` into a buffer reused by its thread,
    so neither reading nor decoding allocates per chunk, and tasks of one read run in parallel.
    """

    _buffers = threading.local()

    def __init__(
        self,
        file: Path,
        lay: _Layout,
        out: np.ndarray,
        start: int,
        stop: int,
        shard: int,
        first: int,
        last: int,
        where: str,
    ) -> None:
        self.file, self.lay, self.out, self.start, self.stop = file, lay, out, start, stop
        self.s0, self.first, self.last = shard * lay.shard_steps, first, last
        self.where = where  # "STORE: array 'NAME'", for messages

    def _buffer(self, name: str, nbytes: int) -> np.ndarray:
        buf = getattr(self._buffers, name, None)
        if buf is None or buf.nbytes < nbytes:
            buf = np.empty(nbytes, dtype=np.uint8)
            setattr(self._buffers, name, buf)
        return buf[:nbytes]

    def _rows(self, k: int) -> tuple[int, int, int]:
        """Chunk k's first step, and the window's rows a:b it covers."""
        c0 = self.s0 + k * self.lay.inner_steps
        c1 = min(c0 + self.lay.inner_steps, self.lay.shape[0])
        return c0, max(c0, self.start), min(c1, self.stop)

    def __call__(self) -> None:
        lay, out, start = self.lay, self.out, self.start
        if not self.file.exists():
            last = min(self.s0 + lay.shard_steps, lay.shape[0]) - 1
            raise DamagedStoreError(
                f"{self.where} is damaged: its shard {self.file} (steps {self.s0}-{last}) is missing"
            )
        with open(self.file, "rb") as f:
            index, data_end = _read_index(f, self.file, lay.shard_steps // lay.inner_steps)
            index = index[self.first : self.last + 1]
            present = index[:, 0] != _MISSING
            lo = int(index[present, 0].min()) if present.any() else 0
            hi = int((index[present, 0] + index[present, 1]).max()) if present.any() else 0
            if hi > data_end:
                raise ValueError(f"{self.file}: shard index points past the chunk data")
            data = self._buffer("data", hi - lo)
            f.seek(lo)
            if f.readinto(data.data) != hi - lo:
                raise ValueError(f"{self.file}: shard ends inside its chunk data")
        step = int(np.prod(lay.shape[1:])) * 4
        for k, (offset, nbytes) in enumerate(index, start=self.first):
            c0, a, b = self._rows(k)
            if offset == _MISSING:
                raise DamagedStoreError(
                    f"{self.where} is damaged: inner chunk {k} of shard {self.file} "
                    f"(steps {c0}-{min(c0 + lay.inner_steps, lay.shape[0]) - 1}) is missing"
                )
            src = data.data[int(offset) - lo : int(offset + nbytes) - lo]
            # Edge chunks are stored whole (padded with fill): decode aside, copy the rows used.
            if (a, b) == (c0, c0 + lay.inner_steps):
                _decode(src, out[a - start : b - start], lay.compressed, str(self.file))
            else:
                scratch = self._buffer("scratch", lay.inner_steps * step).view(np.float32)
                scratch = scratch.reshape(lay.inner_steps, *lay.shape[1:])
                _decode(src, scratch, lay.compressed, str(self.file))
                out[a - start : b - start] = scratch[a - c0 : b - c0]
            _check_finite(out[a - start : b - start], self.where, a)


@functools.lru_cache(maxsize=4)
def _pool(workers: int) -> ThreadPoolExecutor:
    """A pool kept between reads: a loader reads many short windows, each too short to pay for
    starting threads."""
    return ThreadPoolExecutor(workers, thread_name_prefix="dozerlab-read")


def read_field(
    path: str | Path,
    name: str,
    start: int = 0,
    stop: int | None = None,
    *,
    threads: int | None = None,
) -> np.ndarray:
    """Steps ``start:stop`` of array ``name`` of the store at ``path``, as float32 (C order).

    Equal to ``zarr.open_array(path / name)[start:stop]`` for a whole store; raises
    :class:`DamagedStoreError` (a ``ValueError``) naming the array and the piece when a chunk
    the metadata implies is missing or a value is NaN/inf, and ``ValueError`` naming the file on
    a corrupt shard. ``threads`` defaults to the job's thread budget.
    """
    array_dir = Path(path) / name
    meta_file = array_dir / "zarr.json"
    if not meta_file.exists():
        raise FileNotFoundError(f"{path} has no array '{name}'")
    where = f"{path}: array '{name}'"
    lay = _layout(json.loads(meta_file.read_text()))
    if lay is None:
        if missing := missing_pieces(path, name):
            raise DamagedStoreError(f"{where} is damaged: missing {', '.join(missing)}")
        array = zarr.open_array(array_dir, mode="r")
        values = np.ascontiguousarray(array[start:stop])
        if values.dtype.kind == "f":
            first = slice(start, stop).indices(array.shape[0])[0] if array.ndim else 0
            _check_finite(values, where, first)
        return values
    start, stop, _ = slice(start, stop).indices(lay.shape[0])
    stop = max(stop, start)
    out = np.empty((stop - start, *lay.shape[1:]), dtype=np.float32)
    if stop == start:
        return out
    key = "/".join(["0"] * (len(lay.shape) - 1))
    workers = max(1, threads or thread_budget())
    shards = range(start // lay.shard_steps, (stop - 1) // lay.shard_steps + 1)
    # Split shards into pieces of inner chunks so that a short window still uses every thread.
    pieces = max(1, -(-workers // len(shards)))
    tasks = []
    for shard in shards:
        s0 = shard * lay.shard_steps
        first = (max(start, s0) - s0) // lay.inner_steps
        last = (min(stop, s0 + lay.shard_steps) - s0 - 1) // lay.inner_steps
        bounds = np.linspace(first, last + 1, min(pieces, last + 1 - first) + 1).astype(int)
        file = array_dir / "c" / str(shard) / key
        tasks += [
            _Task(file, lay, out, start, stop, shard, int(a), int(b) - 1, where)
            for a, b in itertools.pairwise(bounds)
        ]
    if workers == 1 or len(tasks) == 1:
        for task in tasks:
            task()
    else:
        list(_pool(min(workers, len(tasks))).map(_Task.__call__, tasks))
    return out
