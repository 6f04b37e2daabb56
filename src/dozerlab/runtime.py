"""Process-level settings shared by every command: the thread budget, the heap frozen once a job
is loaded (:func:`freeze_heap`), and safe atomic outputs.

Every file or directory a command writes goes through :func:`atomic_output`, which builds it
whole in a temporary sibling and renames it into place, and which replaces an existing path only
when that path is what the same command wrote before (its :class:`OutputKind` recognises it by
the mark naming that command, or by a schema only it writes). Anything else found there is
refused and left as it was: a mistyped ``--out`` never costs a user their data.

Every job starts inside :func:`job_outputs`, which checks all of the command's outputs before
any work (each one replaceable, its folder writable, no file in the way, names not too long)
and, should the job fail after all, takes back what it had already moved into place, so that a
command that fails leaves nothing behind. Names that become parts of paths pass
:func:`check_name`.
"""

from __future__ import annotations

import contextlib
import contextvars
import ctypes
import errno
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

from threadpoolctl import threadpool_limits


class DozerlabError(Exception):
    """An error the user can act on; the CLI prints its message without a traceback."""


class ConfigError(DozerlabError, ValueError):
    """A configuration value outside what the schema allows (raised by :mod:`dozerlab.config`
    and by :mod:`dozerlab.sweep`, which builds on it; here so that neither imports the other
    for it)."""


def set_threads(n: int) -> int:
    """Limit numba, torch and numpy's BLAS to ``n`` threads (the Snakemake rule's ``threads``).

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
    # numpy's BLAS (the ridge's Gram matrices, learn.fitting.gram) read the variables when
    # numpy was imported, before this: its pool is limited where it stands
    threadpool_limits(n, user_api="blas")
    return n


#: glibc's ``mallopt`` parameters (malloc.h) and the size up to which freed memory is kept.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
KEPT_BYTES = 1 << 30


def keep_freed_memory() -> bool:
    """Have glibc's malloc serve blocks below :data:`KEPT_BYTES` from the heap and keep what is
    freed for the next allocation, instead of mapping each large block afresh and returning it.

    The training jobs call it (:func:`dozerlab.learn.jobs.train_job`). A training step frees and
    allocates the same large blocks every batch (the MLP's 60 MB first-layer gradient); mapped
    afresh, each of its pages faults in zeroed again. With this the MLP trained in 0.77 of the
    time and the ridge in 0.79, the CNN and the U-Nets in about the same, to the same weights
    bit for bit; the process keeps up to its peak use (the ridge's job 3.0 GB, was 2.6). The
    reduced loop's many small blocks ran 13 % slower on the heap, so the other jobs keep
    glibc's defaults (BENCHMARKS.md, "Freed memory kept for the next batch"). Returns whether
    it took effect (glibc only; elsewhere nothing changes)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return all(
        mallopt(option, KEPT_BYTES) == 1 for option in (_M_MMAP_THRESHOLD, _M_TRIM_THRESHOLD)
    )


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


class OutputPathError(DozerlabError):
    """An output cannot be written where it was asked for (a folder not writable, a file in the
    way, a name too long); found before the work, nothing written."""


@dataclass(frozen=True)
class OutputKind:
    """What a command writes, and how to recognise one written before (so only that is replaced).

    ``what`` names it in messages ("a dozerlab field store"); ``recognise(path)`` is True when
    the existing ``path`` is such an output. It must not raise. ``name`` is the mark a writer
    records in outputs that have room for one (a store attribute, a bed's metadata, a PNG text,
    a folder's mark file), naming the command or part of it that wrote the output; ``mark(tmp)``,
    when given, marks the finished temporary before it is moved into place
    (:func:`marked_folder`).
    """

    what: str
    recognise: Callable[[Path], bool]
    name: str = ""
    mark: Callable[[Path], None] | None = None


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


@dataclass
class _Group:
    """The outputs of one job (:func:`job_outputs`): those declared, those already moved into
    place (with the earlier output each replaced, kept aside until the job succeeds)."""

    declared: set[Path]
    placed: list[tuple[Path, Path | None]]


_GROUP: contextvars.ContextVar[_Group | None] = contextvars.ContextVar("dozerlab_outputs")


def _sibling(final: Path, tag: str, pid: int | None = None) -> Path:
    """``.NAME.{tag}-HOST-PID``: a temporary (``tmp``) or a kept earlier output (``old``)."""
    return final.with_name(f".{final.name}.{tag}-{socket.gethostname()}-{pid or os.getpid()}")


@contextmanager
def atomic_output(path: str | Path, kind: OutputKind | None = None) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` to write into; rename it to ``path`` on success.

    Works for files and directories (zarr stores, folders of figures). An existing ``path`` is
    replaced only if ``kind`` recognises it as an output of the same kind (:func:`check_output`,
    checked on entry and again before the rename); otherwise :class:`OutputExistsError` is
    raised and ``path`` is left as it was. A ``kind`` with a ``mark`` marks the temporary before
    the rename. On any exception the temporary is removed, so no half-written output is ever
    mistaken for a result. The temporary is ``.NAME.tmp-HOST-PID``; one left by a writer on this
    host that was killed outright (its PID no longer runs) is removed on the next write. Inside
    :func:`job_outputs`, an output it declared is moved into place with the earlier one kept
    aside (``.NAME.old-HOST-PID``) until the job ends.
    """
    final = Path(path)
    check_output(final, kind)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputExistsError(
            f"cannot write {final}: a file is in the way of its directory {final.parent}"
        ) from None
    # Temporaries and kept outputs of earlier writers on this host that died (SIGKILL).
    for tag in ("tmp", "old"):
        prefix = _sibling(final, tag).name.rsplit("-", 1)[0] + "-"
        for stale in final.parent.glob(glob.escape(prefix) + "*"):
            pid = stale.name[len(prefix) :]
            if pid.isdigit() and process_token(int(pid)) is None:
                _remove(stale)
    tmp = _sibling(final, "tmp")
    _remove(tmp)
    try:
        yield tmp
        if kind is not None and kind.mark is not None and tmp.exists():
            kind.mark(tmp)
        check_output(final, kind)
        group = _GROUP.get(None)
        if group is not None and final.absolute() in group.declared:
            kept = None
            if final.exists() or final.is_symlink():
                kept = _sibling(final, "old")
                _remove(kept)
                os.replace(final, kept)
            os.replace(tmp, final)
            group.placed.append((final, kept))
        else:
            _remove(final)
            os.replace(tmp, final)
    finally:
        _remove(tmp)


def check_name(value: str, argument: str) -> str:
    """Refuse a name that becomes one component of a path (a model, a scenario) unless it is
    one: not empty, no ``/`` or ``\\``, not ``.`` or ``..``, no NUL, at most 255 bytes.
    ``argument`` names where it came from (``--dynamics-model``). Returns ``value``."""
    text = str(value)
    checks = (
        (not text, "is empty"),
        (text in (".", ".."), "is not a name"),
        ("/" in text or "\\" in text, "holds a path separator"),
        ("\0" in text, "holds a NUL character"),
        (len(os.fsencode(text)) > 255, "is longer than 255 bytes"),
    )
    bad = next((reason for failed, reason in checks if failed), "")
    if bad:
        raise DozerlabError(
            f"{argument} {text!r} {bad}: it names a file or folder, so it must be a plain name, "
            "not a path"
        )
    return text


#: Bytes kept free under the path length limit for what a folder output holds inside.
_INNER_PATH_BYTES = 64


def check_output_path(path: str | Path, argument: str = "") -> list[Path]:
    """Refuse an output path that cannot be written, before any work: a file (or a broken link)
    in the way of its folder, the nearest existing folder not writable, a name longer than the
    file system allows (also the temporary's, ``.NAME.tmp-HOST-PID``), a path too long.
    ``argument`` (``--out``) is named in the message. Returns the folders that writing it
    will create, nearest first."""
    p = Path(path)

    def refuse(reason: str) -> OutputPathError:
        where = f" ({argument})" if argument else ""
        return OutputPathError(f"cannot write {p}{where}: {reason}; nothing was written")

    if not p.name or p.name in (".", ".."):
        raise refuse("it names no file or folder")
    missing: list[Path] = []
    folder = p.parent
    try:
        while not folder.exists():
            if folder.is_symlink():
                raise refuse(f"{folder} is a broken link, in the way of its folder")
            if folder == folder.parent:
                raise refuse(f"no part of {folder} exists")
            missing.append(folder)
            folder = folder.parent
    except OSError as exc:  # the path is too long to look at
        if exc.errno != errno.ENAMETOOLONG:
            raise
        size = len(os.fsencode(str(p)))
        raise refuse(f"the path is {size} bytes, more than the bytes a path may have") from None
    if not folder.is_dir():
        raise refuse(f"{folder} is a file, not a folder: it is in the way of the output's folder")
    if not os.access(
        folder, os.W_OK | os.X_OK, effective_ids=os.access in os.supports_effective_ids
    ):
        raise refuse(f"the folder {folder.absolute()} is not writable")
    name_max, path_max = _limit(folder, "PC_NAME_MAX", 255), _limit(folder, "PC_PATH_MAX", 4096)
    longest = _sibling(p, "tmp")
    for part in (*p.parts, longest.name):
        if len(os.fsencode(part)) > name_max:
            raise refuse(
                f"the name {part[:40]}… is {len(os.fsencode(part))} bytes, longer than the "
                f"{name_max} bytes a name may have here (with the temporary's "
                f".NAME.tmp-HOST-PID around it)"
            )
    length = len(os.fsencode(str(longest)))
    if length + _INNER_PATH_BYTES >= path_max:
        raise refuse(f"the path is {length} bytes, too near the {path_max} bytes a path may have")
    return missing


def _limit(folder: Path, name: str, default: int) -> int:
    try:
        return int(os.pathconf(folder, name))
    except (OSError, ValueError):
        return default


#: An output of a job: (the argument naming it, its path or None, its kind).
Declared = tuple[str, str | Path | None, OutputKind | None]


@contextmanager
def job_outputs(*outputs: Declared) -> Iterator[None]:
    """Check all of a job's outputs before its work, and make them one: all or nothing.

    ``outputs`` are ``(argument, path, kind)``; a ``None`` path is skipped. Before the body
    runs, every path must be writable (:func:`check_output_path`) and absent or an earlier
    output of ``kind`` (:func:`check_output`), and no two may be the same path or one inside
    the other; the first that fails raises, naming its argument and path, and nothing has been
    written. Should the body fail, every declared output that :func:`atomic_output` already
    moved into place is removed and the earlier output it replaced put back, and the folders
    made for them are removed if empty: a failed command leaves nothing behind.
    """
    items = [(arg, Path(path), kind) for arg, path, kind in outputs if path is not None]
    created: list[Path] = []
    for arg, path, kind in items:
        created += check_output_path(path, arg)
        check_output(path, kind)
    where = {arg: path.absolute() for arg, path, _ in items}
    for i, (a, pa) in enumerate(where.items()):
        for b, pb in list(where.items())[i + 1 :]:
            if pa == pb or pa in pb.parents or pb in pa.parents:
                raise OutputPathError(
                    f"{a} ({pa}) and {b} ({pb}) would overwrite each other: "
                    "give them separate paths; nothing was written"
                )
    group = _Group({p.absolute() for _, p, _ in items}, [])
    token = _GROUP.set(group)
    try:
        yield
    except BaseException:
        for final, kept in reversed(group.placed):
            _remove(final)
            if kept is not None:
                os.replace(kept, final)
        for folder in sorted(set(created), key=lambda f: len(f.parts), reverse=True):
            try:
                folder.rmdir()
            except OSError as exc:  # not empty (another writer's), or already gone
                if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOENT):
                    raise
        raise
    else:
        for _, kept in group.placed:
            if kept is not None:
                _remove(kept)
    finally:
        _GROUP.reset(token)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    elif p.exists() or p.is_symlink():
        p.unlink()


# Recognisers shared by several layers' kinds. Each reads only a file's head.


#: The PNG text keyword naming the output a figure is (:func:`png_metadata`, :func:`marked_png`).
PNG_OUTPUT_KEY = "dozerlab-output"


def png_metadata(name: str = "") -> dict[str, str]:
    """``savefig(..., metadata=png_metadata())``: the PNG text that marks a figure as ours; with
    ``name``, also which output it is (an :class:`OutputKind`'s ``name``, :func:`marked_png`)."""
    return {"Software": MARK} | ({PNG_OUTPUT_KEY: name} if name else {})


def _png_texts(path: Path) -> list[bytes]:
    """The data of a PNG file's text chunks before its image data ([] for anything else)."""
    texts: list[bytes] = []
    if not path.is_file():
        return texts
    with open(path, "rb") as f:
        if f.read(8) != _PNG_MAGIC:
            return texts
        while header := f.read(8):
            if len(header) < 8:
                break
            length, ctype = int.from_bytes(header[:4], "big"), header[4:]
            if ctype in (b"IDAT", b"IEND"):
                break
            data = f.read(length)
            if ctype in (b"tEXt", b"iTXt", b"zTXt"):
                texts.append(data)
            f.seek(4, os.SEEK_CUR)  # the chunk's CRC
    return texts


def is_marked_png(path: Path) -> bool:
    """A PNG file whose text chunks (before the image data) carry :data:`MARK`."""
    return any(MARK.encode() in data for data in _png_texts(path))


def marked_png(what: str, name: str) -> OutputKind:
    """The kind of a PNG figure that one command writes on its own (``bed --plot``), saved with
    ``png_metadata(name)``: recognised by that text only, not by another command's figure."""
    entry = PNG_OUTPUT_KEY.encode() + b"\0" + name.encode()
    return OutputKind(what, lambda path: entry in _png_texts(path), name)


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


def json_with(keys: Collection[str], without: Collection[str] = ()) -> Callable[[Path], bool]:
    """A recogniser of JSON files holding an object with (at least) ``keys`` and none of
    ``without`` (the keys that tell another command's JSON apart)."""

    def recognise(path: Path) -> bool:
        if not path.is_file():
            return False
        doc = json.loads(path.read_text())
        return isinstance(doc, dict) and set(keys) <= doc.keys() and not set(without) & doc.keys()

    return recognise


#: The file that marks a folder as one of ours (:func:`marked_folder`).
FOLDER_MARK = ".dozerlab-output.json"
#: What Snakemake adds to a ``directory()`` output when its job ends: not the user's, so a
#: folder of ours that the workflow wrote stays ours.
SNAKEMAKE_TIMESTAMP = ".snakemake_timestamp"


def _entries(root: Path) -> list[str]:
    """Every file, folder and link under ``root`` (links not followed), as relative paths."""
    found = []
    for folder, dirs, files in os.walk(root):
        rel = Path(folder).relative_to(root)
        found += [(rel / n).as_posix() for n in (*dirs, *files)]
    return sorted(found)


def marked_folder(what: str, name: str) -> OutputKind:
    """The kind of a folder that a command writes whole (figures, snapshots).

    Its mark, :data:`FOLDER_MARK` inside it, names the output (``name``) and lists every entry
    the command wrote. An existing folder is recognised only if its mark names ``name`` and it
    holds nothing the mark does not list (but Snakemake's :data:`SNAKEMAKE_TIMESTAMP`): a user's
    folder, one of another command, or one of ours that a user has since added a file to is not
    replaced. An empty folder is not ours either.
    """

    def recognise(path: Path) -> bool:
        if path.is_symlink() or not path.is_dir():
            return False
        doc = json.loads((path / FOLDER_MARK).read_text())
        listed = set(doc["entries"]) | {FOLDER_MARK, SNAKEMAKE_TIMESTAMP}
        return doc.get("output") == name and set(_entries(path)) <= listed

    def mark(tmp: Path) -> None:
        doc = {"generator": MARK, "output": name, "entries": _entries(tmp)}
        (tmp / FOLDER_MARK).write_text(json.dumps(doc, indent=1))

    return OutputKind(what, recognise, name, mark)


#: Figures every layer writes (matplotlib PNGs saved with :func:`png_metadata`).
FIGURE = OutputKind("a PNG figure written by dozerlab", is_marked_png)
ANIMATION = OutputKind("a GIF animation written by dozerlab", is_marked_gif)
