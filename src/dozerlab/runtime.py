"""Process-level settings shared by every command: the thread budget and atomic outputs."""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class DozerlabError(Exception):
    """An error the user can act on; the CLI prints its message without a traceback."""


def set_threads(n: int) -> int:
    """Limit numba, torch and BLAS to ``n`` threads (the Snakemake rule's ``threads``).

    Snakemake sets ``OMP_NUM_THREADS`` but not ``NUMBA_NUM_THREADS``. numba fixes its pool
    size when it first starts and refuses a changed ``NUMBA_NUM_THREADS`` after that, so the
    variable is set only while numba is not yet imported (a fresh job process); the active
    count is set in every case. Returns the count in effect.
    """
    if n < 1:
        raise ValueError(f"threads must be >= 1, got {n}")
    env: tuple[str, ...] = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
    if "numba" not in sys.modules:
        env += ("NUMBA_NUM_THREADS",)
    for var in env:
        os.environ[var] = str(n)
    import numba

    # numba.config sets its NUMBA_* attributes at run time, so the stubs cannot know them
    n = min(n, numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]
    numba.set_num_threads(n)
    # torch reads OMP_NUM_THREADS when first imported; only an already imported one is told,
    # so jobs that never use torch do not pay for importing it.
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(n)
    return n


def thread_budget() -> int:
    """The job's thread count: ``OMP_NUM_THREADS`` (Snakemake's ``threads``, or what
    :func:`set_threads` set), else the CPUs this process may run on."""
    try:
        n = int(os.environ.get("OMP_NUM_THREADS", ""))
    except ValueError:
        n = 0
    return n if n >= 1 else len(os.sched_getaffinity(0))


@contextmanager
def atomic_output(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` to write into; rename it to ``path`` on success.

    Works for files and directories (zarr stores). On any exception the temporary is removed
    and ``path`` is left as it was, so no half-written output is ever mistaken for a result.
    """
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    _remove(tmp)
    try:
        yield tmp
        _remove(final)
        os.replace(tmp, final)
    finally:
        _remove(tmp)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    elif p.exists() or p.is_symlink():
        p.unlink()
