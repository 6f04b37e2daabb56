"""Field-store read throughput (and, with ``--sampling``, the cost of sampling next to a solver step).

Writes thesis-size stores (48×48×20 bins per step) of synthetic fields shaped like real ones — a
granular bed filling the lower part of the volume, empty bins above it — and reads them back:

* a table over codecs and ``chunk_steps`` (smaller stores, ``--table-steps``): write MB/s,
  compression ratio, decoded GB/s of a full read through zarr-python and through
  :func:`dozerlab.fields.reader.read_field` (the platform's reader), and of random windows of 64
  consecutive steps with the latter;
* the default codec on ``--steps`` steps, read both ways, beside a raw ``.npy`` read of the same
  data, with the targets: full read >= 1 GB/s and within 2x of the ``.npy`` read.

Decoded GB/s counts the float32 bytes of velocity + density handed back. Readers use
``--threads`` threads (default 2, this machine's budget); zarr-python uses its own pool. Both formats are read
from the page cache right after writing, so the figures compare decoding, not disks; full reads
are the best of three, for both formats, as the machine's load varies.

    python benchmarks/field_store_read.py [--steps 1500] [--table-steps 384] [--sampling]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import zarr
from zarr.codecs import BloscCodec

from dozerlab.fields.reader import read_field
from dozerlab.fields.store import ATTRS, FieldStoreWriter, default_codec

BINS = (48, 48, 20)
BATCH = 64
#: Full reads are timed this many times and the best kept, for zarr and .npy alike.
REPEATS = 3


def synthetic_steps(n: int, seed: int = 0):
    """Yield n (velocity (48,48,20,3), density (48,48,20)) float32 steps of a moving pile."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 1, BINS[0])[:, None, None]
    z = np.linspace(0, 1, BINS[2])[None, None, :]
    for t in range(n):
        surface = 0.35 + 0.25 * np.exp(-(((x - 0.3 - 0.1 * np.sin(t / 50)) / 0.25) ** 2))
        filled = np.broadcast_to(z < surface, BINS)
        rho = np.where(filled, 1500 + 100 * rng.standard_normal(BINS), 0).astype(np.float32)
        vel = np.where(
            filled[..., None], rng.normal(0.0, 0.2, (*BINS, 3)) + [0.8, 0, 0.1], 0
        ).astype(np.float32)
        yield vel, rho


def write(path: Path, steps: int, codec, chunk_steps: int) -> float:
    """Write a store; return the wall time in s."""
    c = [(np.arange(n) + 0.5) * 0.025 for n in BINS]
    zero = np.zeros(3)
    start = time.perf_counter()
    with FieldStoreWriter(
        path,
        x=c[0],
        y=c[1],
        z=c[2],
        attrs=dict.fromkeys(ATTRS),
        chunk_steps=chunk_steps,
        codec=codec,
    ) as w:
        for t, (vel, rho) in enumerate(synthetic_steps(steps)):
            w.append(t * 0.01, vel, rho, zero, zero, zero, zero)
    return time.perf_counter() - start


def du(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def best_rate(read, repeats: int = REPEATS) -> float:
    """Best decoded GB/s of ``repeats`` calls of ``read`` (which returns the bytes it read)."""
    best = 0.0
    for _ in range(repeats):
        start = time.perf_counter()
        nbytes = read()
        best = max(best, nbytes / (time.perf_counter() - start) / 1e9)
    return best


def read_full_zarr(path: Path) -> float:
    """Decoded GB/s of reading all of velocity and density with zarr-python (best of REPEATS)."""
    g = zarr.open_group(path, mode="r")
    return best_rate(lambda: g["velocity"][:].nbytes + g["density"][:].nbytes)


def read_full(path: Path, threads: int) -> float:
    """Decoded GB/s of reading all of velocity and density with read_field (best of REPEATS)."""
    return best_rate(
        lambda: sum(read_field(path, n, threads=threads).nbytes for n in ("velocity", "density"))
    )


def windows(steps: int, batches: int, rng: np.random.Generator) -> list[int]:
    """Start steps of random 64-step windows (a loader streaming a store asks for such runs)."""
    return rng.integers(0, steps - BATCH + 1, size=batches).tolist()


def read_batches(
    path: Path, steps: int, batches: int, rng: np.random.Generator, threads: int
) -> float:
    """Decoded GB/s of random windows of 64 consecutive steps with read_field."""
    nbytes, elapsed = 0, 0.0
    for i in windows(steps, batches, rng):
        start = time.perf_counter()
        nbytes += sum(
            read_field(path, n, i, i + BATCH, threads=threads).nbytes
            for n in ("velocity", "density")
        )
        elapsed += time.perf_counter() - start
    return nbytes / elapsed / 1e9


def npy_reads(tmp: Path, steps: int, batches: int, rng: np.random.Generator) -> tuple[float, float]:
    """(full, batch) GB/s of the same data as raw .npy files (np.load; batches via memory map)."""
    vel = np.lib.format.open_memmap(
        tmp / "velocity.npy", mode="w+", dtype=np.float32, shape=(steps, *BINS, 3)
    )
    rho = np.lib.format.open_memmap(
        tmp / "density.npy", mode="w+", dtype=np.float32, shape=(steps, *BINS)
    )
    for t, (v, r) in enumerate(synthetic_steps(steps)):
        vel[t], rho[t] = v, r
    vel.flush(), rho.flush()
    del vel, rho
    full = best_rate(
        lambda: np.load(tmp / "velocity.npy").nbytes + np.load(tmp / "density.npy").nbytes
    )
    v = np.load(tmp / "velocity.npy", mmap_mode="r")
    r = np.load(tmp / "density.npy", mmap_mode="r")
    nbytes, elapsed = 0, 0.0
    for i in windows(steps, batches, rng):
        start = time.perf_counter()
        nbytes += np.array(v[i : i + BATCH]).nbytes + np.array(r[i : i + BATCH]).nbytes
        elapsed += time.perf_counter() - start
    (tmp / "velocity.npy").unlink()
    (tmp / "density.npy").unlink()
    return full, nbytes / elapsed / 1e9


CODECS = {
    "lz4-5": lambda: BloscCodec(cname="lz4", clevel=5, shuffle="noshuffle"),
    "lz4-1": lambda: BloscCodec(cname="lz4", clevel=1, shuffle="noshuffle"),
    "lz4-5-shuffle": lambda: BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"),
    "zstd-1": lambda: BloscCodec(cname="zstd", clevel=1, shuffle="noshuffle"),
    "zstd-1-shuffle": lambda: BloscCodec(cname="zstd", clevel=1, shuffle="shuffle"),
    "none": lambda: (),
}


def table(tmp: Path, steps: int, batches: int, threads: int) -> None:
    print(
        f"\ncodec × chunk_steps, {steps} steps of {BINS} bins "
        f"({steps * np.prod(BINS) * 16 / 1e9:.2f} GB decoded); GB/s of decoded data"
    )
    print(
        f"{'codec':15} {'chunk':>5} {'write MB/s':>10} {'ratio':>6} {'zarr full':>9} "
        f"{'full':>6} {'64-step':>7}"
    )
    rows = [(name, 64) for name in CODECS] + [("lz4-5", 16), ("lz4-5", 256)]
    for name, chunk in rows:
        path = tmp / f"{name}-{chunk}.zarr"
        wall = write(path, steps, CODECS[name](), chunk)
        raw = steps * np.prod(BINS) * 16
        zfull = read_full_zarr(path)
        full = read_full(path, threads)
        batch = read_batches(path, steps, batches, np.random.default_rng(1), threads)
        print(
            f"{name:15} {chunk:>5} {raw / wall / 1e6:>10.0f} {raw / du(path):>6.2f} {zfull:>9.2f} "
            f"{full:>6.2f} {batch:>7.2f}"
        )
        shutil.rmtree(path)


def headline(tmp: Path, steps: int, batches: int, threads: int) -> None:
    path = tmp / "default.zarr"
    wall = write(path, steps, default_codec(), 64)
    raw = steps * np.prod(BINS) * 16
    zfull = read_full_zarr(path)
    full = read_full(path, threads)
    batch = read_batches(path, steps, batches, np.random.default_rng(2), threads)
    shutil.rmtree(path)
    npy_full, npy_batch = npy_reads(tmp, steps, batches, np.random.default_rng(2))
    print(
        f"\ndefault store ({default_codec().to_dict()['configuration']}, chunk_steps 64), "
        f"{steps} steps = {raw / 1e9:.2f} GB decoded; write {raw / wall / 1e6:.0f} MB/s; {threads} threads"
    )
    print(
        f"  full read     read_field {full:6.2f} GB/s   zarr-python {zfull:6.2f} GB/s   "
        f"npy {npy_full:6.2f} GB/s   npy/read_field {npy_full / full:4.2f}x"
    )
    print(
        f"  64-step batch read_field {batch:6.2f} GB/s   npy {npy_batch:6.2f} GB/s   "
        f"npy/read_field {npy_batch / batch:4.2f}x"
    )
    ok = full >= 1.0 and npy_full / full <= 2.0
    print(f"  target (full >= 1 GB/s and within 2x of npy): {'met' if ok else 'NOT met'}")


def sampling_cost(particles: int, steps: int) -> None:
    """Time one sample of a thesis-size grid against solver steps of a lattice bed of ~particles."""
    from dozerlab.config import load_config
    from dozerlab.fields.sampling import SamplingGrid
    from dozerlab.ndem import World

    cfg = load_config({"sampling": {"bins": list(BINS), "length": 1.2, "below_edge": 0.15}})
    r = float(cfg["bed"]["radius"])
    side = round(particles ** (1 / 3))
    g = (np.arange(side) + 0.5) * 2 * r
    pos = np.array(np.meshgrid(g, g - side * r, g, indexing="ij")).reshape(3, -1).T
    world = World.from_config(cfg)
    world.add_plane(point=(0, 0, 0), normal=(0, 0, 1))
    m = cfg["material"]
    world.add_spheres(
        pos, np.full(len(pos), r), m["density"], m["friction"], m["rolling_resistance"]
    )
    grid = SamplingGrid.from_config(cfg)
    tip = np.array([0.0, 0.0, 0.15])
    world.step()
    grid.sample(world.positions, world.velocities, world.radii, world.masses, tip)  # compile
    start = time.perf_counter()
    for _ in range(steps):
        world.step()
    step_time = (time.perf_counter() - start) / steps
    start = time.perf_counter()
    for _ in range(steps):
        grid.sample(world.positions, world.velocities, world.radii, world.masses, tip)
    sample_time = (time.perf_counter() - start) / steps
    print(
        f"\nsampling {BINS} bins, {len(pos)} particles, {cfg['solver']['iterations']} PGS iterations: "
        f"solver step {1e3 * step_time:.1f} ms, sample {1e3 * sample_time:.2f} ms "
        f"= {100 * sample_time / step_time:.1f} % of a step"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--steps", type=int, default=1500, help="steps of the headline store (default 1500)"
    )
    parser.add_argument(
        "--table-steps", type=int, default=384, help="steps per store of the codec table (0 skips)"
    )
    parser.add_argument(
        "--batches", type=int, default=8, help="random 64-step batches per read test"
    )
    parser.add_argument(
        "--sampling", action="store_true", help="also time sampling against solver steps"
    )
    parser.add_argument(
        "--particles", type=int, default=8000, help="particles of the --sampling bed"
    )
    parser.add_argument("--threads", type=int, default=2, help="read_field threads (default 2)")
    parser.add_argument("--dir", default=None, help="scratch directory (default: a temporary one)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        tmp = Path(d)
        if args.table_steps:
            table(tmp, args.table_steps, args.batches, args.threads)
        headline(tmp, args.steps, args.batches, args.threads)
    if args.sampling:
        sampling_cost(args.particles, 5)


if __name__ == "__main__":
    main()
