"""``read_field`` of this checkout against another checkout's (a baseline), in one process.

Both readers read the same thesis-size store (48×48×20 bins, synthetic fields of
``field_store_read.py``) from the page cache, alternating round by round so that the machine's
load weighs on both alike; the best round of each is kept. Also times, on one inner chunk, what
the integrity check of this checkout adds to a chunk's decoding (a NaN/inf test per chunk).

    python benchmarks/read_field_vs_baseline.py --baseline /path/to/other/checkout/src [--steps 1000] [--rounds 10]
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from numcodecs import Blosc, blosc

from dozerlab.fields import reader
from dozerlab.fields.store import default_codec

sys.path.insert(0, str(Path(__file__).parent))
import field_store_read as bench


def _baseline(src: str):  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location(
        "baseline_reader", Path(src) / "dozerlab" / "fields" / "reader.py"
    )
    module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    sys.modules["baseline_reader"] = module
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


def _best(f, n: int = 200) -> float:  # type: ignore[no-untyped-def]
    best = np.inf
    for _ in range(n):
        t = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", required=True, help="the other checkout's src directory")
    parser.add_argument("--steps", type=int, default=1000, help="steps of the store (default 1000)")
    parser.add_argument("--rounds", type=int, default=10, help="alternating rounds (default 10)")
    args = parser.parse_args()
    readers = {"baseline": _baseline(args.baseline), "this": reader}
    starts = [int(s) for s in np.random.default_rng(0).integers(0, args.steps - 64, 16)]
    best = {(r, k): 0.0 for r in readers for k in ("full", "window")}
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "s.zarr"
        bench.write(path, args.steps, default_codec(), 64)
        names = ("velocity", "density")
        nbytes = sum(reader.read_field(path, n, threads=2).nbytes for n in names)
        for _ in range(args.rounds):
            for label, mod in readers.items():
                t = time.perf_counter()
                for n in names:
                    mod.read_field(path, n, threads=2)
                rate = nbytes / (time.perf_counter() - t) / 1e9
                best[label, "full"] = max(best[label, "full"], rate)
                t = time.perf_counter()
                for s in starts:
                    for n in names:
                        mod.read_field(path, n, s, s + 64, threads=2)
                rate = len(starts) * 64 / args.steps * nbytes / (time.perf_counter() - t) / 1e9
                best[label, "window"] = max(best[label, "window"], rate)
    print(
        f"{args.steps} steps of 48x48x20 bins = {nbytes / 1e9:.2f} GB decoded, 2 threads, "
        f"best of {args.rounds} alternating rounds"
    )
    for kind in ("full", "window"):
        a, b = best["baseline", kind], best["this", kind]
        print(
            f"  {kind:6s} read  baseline {a:.2f} GB/s   this {b:.2f} GB/s   this/baseline {b / a:.2f}"
        )
    chunk = np.random.default_rng(0).random((8, *bench.BINS, 3), dtype=np.float32)
    chunk[:, :, :, bench.BINS[2] // 2 :] = 0.0  # the empty upper half of a sampling volume
    encoded, out = Blosc(cname="lz4", clevel=5, shuffle=0).encode(chunk), np.empty_like(chunk)
    decode = _best(lambda: blosc.decompress(encoded, out))
    check = _best(lambda: reader._check_finite(out, "chunk", 0))
    print(
        f"  one inner chunk ({chunk.nbytes / 1e6:.1f} MB): decode {1e3 * decode:.3f} ms, "
        f"NaN/inf check {1e3 * check:.3f} ms (+{100 * check / decode:.0f} % of decoding)"
    )


if __name__ == "__main__":
    main()
