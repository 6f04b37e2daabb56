"""Fast whole-array and time-window reads of a field store's sharded fields.

zarr-python 3 reads a field store correctly but tops out near 1.2 GB/s on two cores whatever the
codec (``benchmarks/field_store_read.py``): its async pipeline copies each inner chunk several
times. The stores this package writes have one layout — shards along time only, inner chunks of a
few whole steps, ``bytes`` then optionally ``blosc`` then ``crc32c``, a CRC-checked index at the shard's end — and
for that layout :func:`read_field` reads the shard files itself and has Blosc decode every inner
chunk straight into the output array, on a thread per core (Blosc releases the GIL).

Any other layout (a store rewritten by another tool, a non-sharded array) is read through zarr,
so the result is always the same array ``zarr.open_array(path / name)[start:stop]`` returns.

A store never silently reads as zeros: the writer writes every chunk, even an empty one, so a
chunk file or an inner chunk that the metadata implies but the store lacks is damage
(:func:`damaged_pieces`), and :func:`read_field` refuses it, as it refuses NaN and inf.

Nor does it read changed bytes as numbers: every array's chunks (and every inner chunk of a
shard) end in a CRC32C of their encoded bytes (zarr's ``crc32c`` codec, the last of the chain),
which :func:`read_field` checks before decoding and :func:`damaged_pieces` checks for a whole
array, naming the chunk that fails. An array written without that codec (a store of a dozerlab
older than checksums, or rewritten by another tool) is refused (:class:`UncheckedStoreError`),
not read unchecked: its bytes cannot be told from damaged ones, and a flipped bit in a
compressed chunk decodes to finite nonsense (velocities of 1e26 m/s) that no later range check
is sure to catch. The job that wrote it re-creates it with checksums.
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

from dozerlab.integrity import sha256_json
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
            and names in (["bytes", "crc32c"], ["bytes", "blosc", "crc32c"])
            and conf["codecs"][0].get("configuration", {}).get("endian", "little") == "little"
            and index == ["bytes", "crc32c"]
            and conf["index_codecs"][0].get("configuration", {}).get("endian", "little") == "little"
            and conf.get("index_location", "end") == "end"
        )
    except (KeyError, TypeError, ValueError):
        return None
    if not ok:
        return None
    return _Layout(shape, int(shard[0]), int(inner[0]), "blosc" in names, float(meta["fill_value"]))


class DamagedStoreError(ValueError):
    """A store whose files do not hold what its metadata says (a missing chunk, a chunk failing
    its checksum, NaN, …)."""


class UncheckedStoreError(DamagedStoreError):
    """A store, or an array of one, written without checksums: its bytes cannot be verified."""


#: What a user does about a store that fails its checks or has none.
REMEDY = (
    "re-run the job that wrote it (delete the store and re-run the workflow, or `dozerlab "
    "simulate`/`reduce`/`import-legacy`), or copy it again from where it was written; "
    "`dozerlab verify` checks a whole results folder"
)


#: The group attribute holding the SHA-256 of each array's ``zarr.json`` (by array name) and of
#: the group's other attributes (key ``""``), recorded when the store is complete.
DIGEST_ATTR = "metadata_sha256"


def read_metadata(file: Path) -> dict[str, Any]:
    """A ``zarr.json`` document; :class:`DamagedStoreError` naming the file when it is not one."""
    try:
        doc = json.loads(file.read_bytes())
    except (OSError, ValueError) as exc:
        raise DamagedStoreError(f"{file} is not readable zarr metadata ({exc}); {REMEDY}") from exc
    if not isinstance(doc, dict):
        raise DamagedStoreError(f"{file} is not readable zarr metadata (not an object); {REMEDY}")
    return doc


def metadata_digests(path: str | Path, arrays: list[str]) -> dict[str, str]:
    """The :data:`DIGEST_ATTR` value of the store at ``path``: the SHA-256 of each of ``arrays``'
    ``zarr.json`` and, under ``""``, of the group's attributes other than this one."""
    path = Path(path)
    attrs = dict(read_metadata(path / "zarr.json").get("attributes") or {})
    attrs.pop(DIGEST_ATTR, None)
    digests = {"": sha256_json(attrs)}
    digests |= {name: sha256_json(read_metadata(path / name / "zarr.json")) for name in arrays}
    return digests


def check_metadata(path: str | Path) -> list[str]:
    """Refuse a store whose metadata cannot be verified; return the names of its arrays.

    Raises :class:`UncheckedStoreError` for a store without recorded digests or an array without
    chunk checksums, and :class:`DamagedStoreError` naming the ``zarr.json`` whose content differs
    from what was recorded at writing (a changed dtype, shape or attribute), or whose consolidated
    copy in the group's ``zarr.json`` (what xarray reads) differs from the array's own.
    """
    path = Path(path)
    group = read_metadata(path / "zarr.json")
    recorded = (group.get("attributes") or {}).get(DIGEST_ATTR)
    if not isinstance(recorded, dict) or "" not in recorded:
        raise UncheckedStoreError(
            f"{path} was written without checksums (by a dozerlab older than them, or by "
            f"another tool), so its bytes cannot be verified; {REMEDY}"
        )
    arrays = sorted(k for k in recorded if k)
    for name in arrays:
        if not (path / name / "zarr.json").is_file():
            raise DamagedStoreError(
                f"{path}: array '{name}' is missing ({path / name / 'zarr.json'} not found); "
                f"{REMEDY}"
            )
        if not checksummed(read_metadata(path / name / "zarr.json")):
            raise UncheckedStoreError(
                f"{path}: array '{name}' was written without checksums; {REMEDY}"
            )
    actual = metadata_digests(path, arrays)
    for name in ["", *arrays]:
        if actual[name] != recorded[name]:
            file = path / name / "zarr.json" if name else path / "zarr.json"
            what = f"array '{name}'s metadata" if name else "the store's attributes"
            raise DamagedStoreError(
                f"{file} is damaged: {what} changed after writing (SHA-256 differs from the "
                f"one recorded); {REMEDY}"
            )
    consolidated = ((group.get("consolidated_metadata") or {}).get("metadata")) or {}
    for name, doc in consolidated.items():
        own = path / name / "zarr.json"
        if name not in recorded or not own.is_file() or sha256_json(doc) != recorded[name]:
            raise DamagedStoreError(
                f"{path / 'zarr.json'} is damaged: its consolidated copy of array '{name}'s "
                f"metadata differs from {own} as written; {REMEDY}"
            )
    return arrays


def _chain(meta: dict[str, Any]) -> tuple[list[str], dict[str, Any] | None]:
    """The names of the codecs that encode each (inner) chunk of an array, and its sharding
    configuration (None when it is not sharded)."""
    codecs = meta.get("codecs") or []
    if len(codecs) == 1 and codecs[0].get("name") == "sharding_indexed":
        conf = codecs[0].get("configuration") or {}
        return [c.get("name") for c in conf.get("codecs") or []], conf
    return [c.get("name") for c in codecs], None


def checksummed(meta: dict[str, Any]) -> bool:
    """Whether an array's chunks (inner chunks of a shard, and the shard index) end in a CRC32C."""
    names, shard = _chain(meta)
    if shard is not None:
        index = [c.get("name") for c in shard.get("index_codecs") or []]
        if index[-1:] != ["crc32c"]:
            return False
    return names[-1:] == ["crc32c"]


def _crc_ok(data: bytes | memoryview) -> bool:
    """Whether ``data`` ends in the little-endian CRC32C of the bytes before it (no copy)."""
    raw = np.frombuffer(data, dtype=np.uint8)
    return raw.size >= 4 and google_crc32c.value(raw[:-4]) == int.from_bytes(
        raw[-4:].tobytes(), "little"
    )


def _chunk_key(meta: dict[str, Any], idx: tuple[int, ...]) -> str:
    """The store key (relative to the array) of chunk ``idx`` under its key encoding."""
    enc = meta["chunk_key_encoding"]
    if enc["name"] == "default":
        sep = enc.get("configuration", {}).get("separator", "/")
        return sep.join(["c", *map(str, idx)])
    sep = enc.get("configuration", {}).get("separator", ".")
    return sep.join(map(str, idx)) or "0"


def damaged_pieces(path: str | Path, name: str) -> list[str]:
    """Chunks of array ``name`` of the store at ``path`` that are lost or fail their checksum.

    Every chunk of the array's shape must have its file, and each file (each inner chunk of a
    shard, and the shard's index) must match its CRC32C; an inner chunk absent from a shard's
    index is lost too. Reads every chunk's encoded bytes once, decodes nothing. Returns readable
    descriptions (``"chunk c/1/0/0/0/0 (steps 64-127) fails its CRC32C checksum"``); empty for
    a whole array. Checksums are checked only where the array has them (:func:`checksummed`).
    """
    array_dir = Path(path) / name
    meta = json.loads((array_dir / "zarr.json").read_text())
    shape = [int(n) for n in meta["shape"]]
    grid = [int(n) for n in meta["chunk_grid"]["configuration"]["chunk_shape"]]
    names, shard = _chain(meta)
    crc = names[-1:] == ["crc32c"]
    damaged = []
    for idx in itertools.product(*(range(-(-s // c)) for s, c in zip(shape, grid, strict=True))):
        key = _chunk_key(meta, idx)
        steps = (
            f" (steps {idx[0] * grid[0]}-{min(shape[0], (idx[0] + 1) * grid[0]) - 1})"
            if idx
            else ""
        )
        file = array_dir / key
        if not file.is_file():
            damaged.append(f"chunk {key}{steps} is missing")
            continue
        data = file.read_bytes()
        if shard is None:
            if crc and not _crc_ok(data):
                damaged.append(f"chunk {key}{steps} fails its CRC32C checksum")
            continue
        damaged += _shard_damage(data, key, idx, shape, grid, shard, crc)
    return damaged


def _shard_damage(
    data: bytes,
    key: str,
    idx: tuple[int, ...],
    shape: list[int],
    grid: list[int],
    shard: dict[str, Any],
    crc: bool,
) -> list[str]:
    """The lost or corrupt pieces of one shard file's bytes (``grid`` is the shard's shape)."""
    inner = [int(n) for n in shard["chunk_shape"]]
    counts = [-(-g // c) for g, c in zip(grid, inner, strict=True)]
    n_inner = int(np.prod(counts))
    index_crc = [c.get("name") for c in shard.get("index_codecs") or []][-1:] == ["crc32c"]
    size = 16 * n_inner + 4 * index_crc
    if len(data) < size:
        return [f"shard {key} of {len(data)} bytes is shorter than its index (cut short)"]
    raw = data[len(data) - size :] if shard.get("index_location", "end") == "end" else data[:size]
    if index_crc and not _crc_ok(raw):
        return [f"shard {key}: its index fails its CRC32C checksum"]
    index = np.frombuffer(raw, dtype="<u8", count=2 * n_inner).reshape(n_inner, 2)
    per_step_row = n_inner // counts[0]  # inner chunks in C order: axis 0 (time) slowest
    out = []
    for k, (offset, nbytes) in enumerate(index):
        a = idx[0] * grid[0] + (k // per_step_row) * inner[0]
        if a >= shape[0]:
            continue
        where = f"inner chunk {k} of shard {key} (steps {a}-{min(shape[0], a + inner[0]) - 1})"
        if offset == _MISSING:
            out.append(f"{where} is missing")
        elif int(offset) + int(nbytes) > len(data):
            out.append(f"{where} lies past the end of the shard (cut short)")
        elif crc and not _crc_ok(memoryview(data)[int(offset) : int(offset) + int(nbytes)]):
            out.append(f"{where} fails its CRC32C checksum")
    return out


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
        raise DamagedStoreError(f"{file}: shard of {size} bytes is shorter than its index")
    raw = os.pread(f.fileno(), index_bytes + 4, size - index_bytes - 4)
    if google_crc32c.value(raw[:-4]) != int.from_bytes(raw[-4:], "little"):
        raise DamagedStoreError(f"{file}: shard index fails its CRC32C check")
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
                raise DamagedStoreError(f"{self.file}: shard index points past the chunk data")
            data = self._buffer("data", hi - lo)
            f.seek(lo)
            if f.readinto(data.data) != hi - lo:
                raise DamagedStoreError(f"{self.file}: shard ends inside its chunk data")
        step = int(np.prod(lay.shape[1:])) * 4
        for k, (offset, nbytes) in enumerate(index, start=self.first):
            c0, a, b = self._rows(k)
            if offset == _MISSING:
                raise DamagedStoreError(
                    f"{self.where} is damaged: inner chunk {k} of shard {self.file} "
                    f"(steps {c0}-{min(c0 + lay.inner_steps, lay.shape[0]) - 1}) is missing"
                )
            src = data.data[int(offset) - lo : int(offset + nbytes) - lo]
            if not _crc_ok(src):
                raise DamagedStoreError(
                    f"{self.where} is damaged: inner chunk {k} of shard {self.file} "
                    f"(steps {c0}-{min(c0 + lay.inner_steps, lay.shape[0]) - 1}) fails its CRC32C "
                    f"checksum: its bytes changed after they were written; {REMEDY}"
                )
            src = src[:-4]
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
    meta = read_metadata(meta_file)
    if not checksummed(meta):
        raise UncheckedStoreError(f"{where} was written without checksums; {REMEDY}")
    lay = _layout(meta)
    if lay is None:
        if damaged := damaged_pieces(path, name):
            raise DamagedStoreError(f"{where} is damaged: {', '.join(damaged)}; {REMEDY}")
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
