"""Process-level settings shared by every command: the thread budget, the heap frozen once a job
is loaded (:func:`freeze_heap`), and safe atomic outputs.

Every file or directory a command writes goes through :func:`atomic_output`, which builds it
in a temporary sibling and renames it into place, and which replaces an existing path only when
that path is what the command writes (its :class:`OutputKind` recognises it by its own marker or
schema). Anything else found there is refused and left as it was: a mistyped ``--out`` never
costs a user their data.
"""

from __future__ import annotations

import contextlib
import gc
import glob
import json
import os
import shutil
import signal
import socket
import sys
import threading
import time
import zipfile
from collections.abc import Callable, Collection, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path


class DozerlabError(Exception):
    """An error the user can act on; the CLI prints its message without a traceback."""


class ConfigError(DozerlabError, ValueError):
    """A configuration value outside what the schema allows (raised by :mod:`dozerlab.config`
    and by :mod:`dozerlab.sweep`, which builds on it; here so that neither imports the other
    for it)."""


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


def freeze_heap() -> None:
    """Exempt every object alive now from Python's cyclic garbage collector (``gc.freeze``).

    Call it once a job's imports, models and inputs are loaded, before its loop. Those objects
    live until the process ends, yet every full collection walks them (torch alone leaves some
    10⁵) and so does the interpreter's last one at exit: on a reduce job of the default sweep,
    0.4 s of full collections in a 4 s loop and 0.5 s at exit. Objects made afterwards are
    collected as before.
    """
    gc.freeze()


def thread_budget() -> int:
    """The job's thread count: ``OMP_NUM_THREADS`` (Snakemake's ``threads``, or what
    :func:`set_threads` set), else the CPUs this process may run on."""
    try:
        n = int(os.environ.get("OMP_NUM_THREADS", ""))
    except ValueError:
        n = 0
    return n if n >= 1 else len(os.sched_getaffinity(0))


#: The workflow's process (Snakemake) and host, set by the Snakefile for its jobs.
WORKFLOW_PID_ENV = "DOZERLAB_WORKFLOW_PID"
WORKFLOW_HOST_ENV = "DOZERLAB_WORKFLOW_HOST"


def process_token(pid: int) -> str | None:
    """An identity of the live process ``pid`` that a reused pid does not share (its start
    time in clock ticks since boot, Linux); None when no such process runs."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:
            pass
        return "alive"  # no /proc: liveness only
    fields = stat[stat.rindex(")") + 2 :].split()
    return None if fields[0] in ("Z", "X") else fields[19]


def workflow_process() -> tuple[int, str] | None:
    """(pid, :func:`process_token`) of the Snakemake process this job belongs to, if it runs on
    this host and lives; None for a job started by hand or on another host (SLURM)."""
    try:
        pid = int(os.environ.get(WORKFLOW_PID_ENV, ""))
    except ValueError:
        return None
    if os.environ.get(WORKFLOW_HOST_ENV) != socket.gethostname() or pid == os.getpid():
        return None
    token = process_token(pid)
    return None if token is None else (pid, token)


def die_with_workflow(poll_s: float = 1.0) -> bool:
    """Stop this job when its Snakemake process is gone (killed with SIGKILL, say).

    Snakemake reaps its jobs when it is interrupted, but a SIGKILLed Snakemake reaps nothing and
    its jobs would run on, orphaned. A daemon thread checks the workflow's process every
    ``poll_s`` seconds; when it is gone, SIGTERM is sent to this process, whose handler exits
    through ``SystemExit`` so that :func:`atomic_output` removes its temporary. Returns whether
    a watch was started (a job of a live workflow on this host). Call from the main thread.
    """
    proc = workflow_process()
    if proc is None:
        return False
    pid, token = proc

    def stop(signum: int, frame: object) -> None:
        raise SystemExit(128 + signum)

    def watch() -> None:
        while process_token(pid) == token:
            time.sleep(poll_s)
        print(
            f"dozerlab: the workflow's snakemake process {pid} is gone; stopping this job",
            file=sys.stderr,
        )
        os.kill(os.getpid(), signal.SIGTERM)

    signal.signal(signal.SIGTERM, stop)
    threading.Thread(target=watch, name="dozerlab-workflow-watch", daemon=True).start()
    return True


def _group_descendants(pid: int) -> list[int]:
    """The descendants of ``pid`` in this process's process group, parents first (Linux
    ``/proc``; none where it is missing)."""
    children: dict[int, list[int]] = {}
    group = os.getpgrp()
    for entry in Path("/proc").glob("[0-9]*"):
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue  # ended meanwhile
        ppid, pgrp = (int(f) for f in stat[stat.rindex(")") + 2 :].split()[1:3])
        if pgrp == group:
            children.setdefault(ppid, []).append(int(entry.name))
    found, todo = [], list(children.get(pid, []))
    while todo:
        found.append(child := todo.pop(0))
        todo += children.get(child, [])
    return found


def sigterm_as_ctrl_c() -> None:
    """Make SIGTERM to this process (the workflow's Snakemake) do what Ctrl-C does.

    Snakemake 9 takes SIGTERM as "finish the running jobs, then exit", while Ctrl-C (SIGINT to
    the terminal's whole process group) stops the jobs at once, removes their outputs and ends
    the parent MLflow run FAILED. From here on SIGTERM sends SIGINT to this process's children
    in its process group (the local jobs, as Ctrl-C would reach them; a job of its own session,
    like the MLflow follower, is left to the hooks) and raises KeyboardInterrupt here, where
    Snakemake handles it as Ctrl-C (a remote executor then cancels its jobs). Call from the
    main thread, after Snakemake installed its own handler (in ``onstart``).
    """

    def interrupt(signum: int, frame: object) -> None:
        for pid in _group_descendants(os.getpid()):
            with contextlib.suppress(ProcessLookupError):  # ended meanwhile
                os.kill(pid, signal.SIGINT)
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)


#: The marker dozerlab writes into outputs that have room for one (PNG text, GIF comment, HTML).
MARK = "dozerlab"
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


class OutputExistsError(DozerlabError):
    """An output path holds something the command did not write; it is left untouched."""


@dataclass(frozen=True)
class OutputKind:
    """What a command writes, and how to recognise one written before (so only that is replaced).

    ``what`` names it in messages ("a dozerlab field store"); ``recognise(path)`` is True when
    the existing ``path`` is such an output. It must not raise.
    """

    what: str
    recognise: Callable[[Path], bool]


def check_output(path: str | Path, kind: OutputKind | None) -> None:
    """Refuse ``path`` as an output unless it is absent or ``kind`` recognises it.

    Commands call this before their work (so a wrong ``--out`` fails at once) and
    :func:`atomic_output` again before its rename. ``kind`` None: only an absent path is accepted.
    Raises :class:`OutputExistsError` naming the path and what was expected there.
    """
    p = Path(path)
    if not (p.exists() or p.is_symlink()):
        return
    try:
        ours = kind is not None and not p.is_symlink() and bool(kind.recognise(p))
    except Exception:  # a recogniser that trips over foreign content has recognised nothing
        ours = False
    if not ours:
        found = "a directory" if p.is_dir() else "a file"
        wanted = kind.what if kind is not None else "nothing (this output is never replaced)"
        raise OutputExistsError(
            f"refusing to replace {p}: it is {found} that is not {wanted}; it was left untouched "
            "(move it away or choose another output path)"
        )


@contextmanager
def atomic_output(path: str | Path, kind: OutputKind | None = None) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` to write into; rename it to ``path`` on success.

    Works for files and directories (zarr stores). An existing ``path`` is replaced only if
    ``kind`` recognises it as an output of the same kind (:func:`check_output`, checked on entry
    and again before the rename); otherwise :class:`OutputExistsError` is raised and ``path`` is
    left as it was. On any exception the temporary is removed, so no half-written output is
    ever mistaken for a result. The temporary is ``.NAME.tmp-HOST-PID``; one left by a writer
    on this host that was killed outright (its PID no longer runs) is removed on the next write.
    """
    final = Path(path)
    check_output(final, kind)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputExistsError(
            f"cannot write {final}: a file is in the way of its directory {final.parent}"
        ) from None
    prefix = f".{final.name}.tmp-{socket.gethostname()}-"
    # Temporaries of earlier writers on this host that died without cleaning up (SIGKILL).
    for stale in final.parent.glob(glob.escape(prefix) + "*"):
        pid = stale.name[len(prefix) :]
        if pid.isdigit() and process_token(int(pid)) is None:
            _remove(stale)
    tmp = final.with_name(f"{prefix}{os.getpid()}")
    _remove(tmp)
    try:
        yield tmp
        check_output(final, kind)
        _remove(final)
        os.replace(tmp, final)
    finally:
        _remove(tmp)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    elif p.exists() or p.is_symlink():
        p.unlink()


# Recognisers shared by several layers' kinds. Each reads only a file's head.


def png_metadata() -> dict[str, str]:
    """``savefig(..., metadata=png_metadata())``: the PNG text that marks a figure as ours."""
    return {"Software": MARK}


def is_marked_png(path: Path) -> bool:
    """A PNG file whose text chunks (before the image data) carry :data:`MARK`."""
    if not path.is_file():
        return False
    with open(path, "rb") as f:
        if f.read(8) != _PNG_MAGIC:
            return False
        while header := f.read(8):
            if len(header) < 8:
                return False
            length, ctype = int.from_bytes(header[:4], "big"), header[4:]
            if ctype in (b"IDAT", b"IEND"):
                return False
            data = f.read(length)
            if ctype in (b"tEXt", b"iTXt", b"zTXt") and MARK.encode() in data:
                return True
            f.seek(4, os.SEEK_CUR)  # the chunk's CRC
    return False


def is_marked_gif(path: Path) -> bool:
    """A GIF file whose comment is :data:`MARK` (see :func:`gif_comment`)."""
    if not path.is_file():
        return False
    from PIL import Image

    with Image.open(path) as im:
        comment = im.info.get("comment", b"")
        return im.format == "GIF" and MARK.encode() in (
            comment if isinstance(comment, bytes) else str(comment).encode()
        )


def first_line_is(line: str) -> Callable[[Path], bool]:
    """A recogniser of text files whose first line is ``line`` (a CSV header, say)."""

    def recognise(path: Path) -> bool:
        if not path.is_file():
            return False
        with open(path, "rb") as f:
            return f.readline(len(line) + 2).rstrip(b"\r\n") == line.encode()

    return recognise


def text_starts_with(prefix: str, within: int = 512) -> Callable[[Path], bool]:
    """A recogniser of text files whose first ``within`` bytes contain ``prefix``."""

    def recognise(path: Path) -> bool:
        if not path.is_file():
            return False
        with open(path, "rb") as f:
            return prefix.encode() in f.read(within)

    return recognise


def npz_with(keys: Collection[str]) -> Callable[[Path], bool]:
    """A recogniser of ``.npz`` files holding (at least) the arrays ``keys``."""

    def recognise(path: Path) -> bool:
        if not path.is_file() or not zipfile.is_zipfile(path):
            return False
        with zipfile.ZipFile(path) as z:
            return {f"{k}.npy" for k in keys} <= set(z.namelist())

    return recognise


def json_with(keys: Collection[str]) -> Callable[[Path], bool]:
    """A recogniser of JSON files holding an object with (at least) ``keys``."""

    def recognise(path: Path) -> bool:
        if not path.is_file():
            return False
        doc = json.loads(path.read_text())
        return isinstance(doc, dict) and set(keys) <= doc.keys()

    return recognise


def is_figure_dir(path: Path) -> bool:
    """A directory of figures and animations this package wrote, and nothing else."""
    if not path.is_dir():
        return False
    files = [p for p in path.rglob("*") if p.is_file()]
    return all(is_marked_png(p) or is_marked_gif(p) for p in files)


#: Figures every layer writes (matplotlib PNGs saved with :func:`png_metadata`).
FIGURE = OutputKind("a PNG figure written by dozerlab", is_marked_png)
ANIMATION = OutputKind("a GIF animation written by dozerlab", is_marked_gif)
FIGURE_DIR = OutputKind("a folder of dozerlab figures", is_figure_dir)
