"""``python -m dozerlab verify PATH…``: check results artifacts, or whole results folders, byte
for byte, as after copying them off a cluster.

Each artifact is checked by the same code that loads it, so what ``verify`` passes the commands
read, and what it refuses they refuse with the same message:

========================  ===============================================================
artifact                  check
========================  ===============================================================
field store (``.zarr``)   :func:`dozerlab.fields.store.verify_store`: the metadata against
                          its recorded SHA-256s, every chunk against its CRC32C, no chunk
                          missing, time increasing, every value finite
bed, final state          :meth:`dozerlab.scenarios.bed.Bed.load`: every array's CRC-32,
(``.npz``)                finite values, positive radii and masses
World file (``.npz``)     :func:`dozerlab.ndem.persist.load_world`
trajectory (``.csv``)     :meth:`dozerlab.scenarios.trajectory.Trajectory.load_csv`: the
                          SHA-256 on its last line, every row following from the ones before
model directory           :func:`dozerlab.learn.pyfunc.verify_model_dir`: every file against
                          the SHA-256 in ``meta.json``, and ``meta.json`` against its own
JSON results              parsed (:func:`dozerlab.integrity.read_json`)
========================  ===============================================================

A folder is searched recursively for these; other files (figures, logs, the report page) are
counted, not checked (a path given that is neither is refused). One line per damaged artifact (``DAMAGED path: what``), one per artifact
written without checksums (``UNCHECKED path: …``, see :mod:`dozerlab.fields.reader`), then a
summary; exit status 0 when every artifact is whole, 1 otherwise.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

_KNOWN = (
    "not an artifact verify checks (a field store, a model directory, a bed or state .npz, a "
    "trajectory .csv, a .json) nor a folder"
)


def register(sub: argparse._SubParsersAction) -> None:
    from dozerlab.cliargs import add_command

    p = add_command(
        sub,
        "verify",
        "check results artifacts or whole results folders for damage (checksums)",
        "python -m dozerlab verify results",
    )
    p.add_argument("paths", nargs="+", metavar="PATH", help="an artifact or a results folder")
    p.set_defaults(func=_verify)


def kind(path: Path) -> str | None:
    """The kind of results artifact at ``path`` (``"store"``, ``"model"``, ``"npz"``,
    ``"trajectory"``, ``"json"``), or None for anything else (a plain folder, a figure)."""
    if path.is_dir():
        if (path / "MLmodel").exists() or (path / "artifacts" / "weights.pt").exists():
            return "model"
        if path.suffix == ".zarr" or (path / "zarr.json").is_file():
            return "store"
        return None
    if path.suffix == ".npz":
        return "npz"
    if path.suffix == ".json":
        return "json"
    if path.suffix == ".csv":  # the only CSV of a results folder (sweep.PATHS)
        return "trajectory"
    return None


def check(path: Path, what: str) -> None:
    """Check one artifact of kind ``what`` with its loader's checks; raises what they raise."""
    if what == "store":
        from dozerlab.fields.store import verify_store

        verify_store(path)
    elif what == "model":
        from dozerlab.learn.pyfunc import verify_model_dir

        verify_model_dir(path)
    elif what == "npz":
        from dozerlab.integrity import read_npz

        keys = read_npz(path, "a dozerlab .npz file", ()).keys()
        if "format_version" in keys:
            from dozerlab.ndem.persist import load_world

            load_world(path)
        else:
            from dozerlab.scenarios.bed import Bed

            Bed.load(path)
    elif what == "trajectory":
        from dozerlab.scenarios.trajectory import Trajectory

        Trajectory.load_csv(path)
    elif what == "json":
        from dozerlab.integrity import read_json

        read_json(path, "a results document")


@dataclass
class Tally:
    """What a verification found: artifacts by outcome, and files it does not check."""

    fine: int = 0
    damaged: list[str] = field(default_factory=list)
    unchecked: list[str] = field(default_factory=list)
    other: int = 0

    @property
    def ok(self) -> bool:
        """Every artifact whole and checked."""
        return not self.damaged and not self.unchecked


def artifacts(root: Path) -> Iterator[tuple[Path, str | None]]:
    """``root`` and, for a folder that is no artifact, everything below it: (path, kind), kind
    None for a file that is not checked. Artifacts' own insides are not listed."""
    what = kind(root)
    if what is not None or not root.is_dir():
        yield root, what
        return
    for folder, dirs, files in os.walk(root):
        here = Path(folder)
        keep = []
        for d in sorted(dirs):
            sub = here / d
            if (k := kind(sub)) is not None:
                yield sub, k
            elif not d.startswith("."):  # .snakemake and the like: not results
                keep.append(d)
        dirs[:] = keep
        for f in sorted(files):
            yield here / f, kind(here / f)


def verify(paths: list[Path], out: TextIO | None = None) -> Tally:
    """Check ``paths`` (artifacts or folders), printing a line per damaged or unchecked
    artifact to ``out``; returns the tally."""
    from dozerlab.fields.reader import UncheckedStoreError
    from dozerlab.runtime import DozerlabError

    out = out or sys.stdout
    tally = Tally()
    for root in paths:
        if not root.exists():
            tally.damaged.append(str(root))
            print(f"MISSING {root}: no such file or directory", file=out)
            continue
        for path, what in artifacts(root):
            if what is None and path == root:
                tally.damaged.append(str(path))
                print(f"UNKNOWN {path}: {_KNOWN}", file=out)
                continue
            if what is None:
                tally.other += 1
                continue
            try:
                check(path, what)
            except UncheckedStoreError as exc:
                tally.unchecked.append(str(path))
                print(f"UNCHECKED {path}: {exc}", file=out)
            except Exception as exc:  # any failure to read it back is damage
                tally.damaged.append(str(path))
                message = str(exc).replace("\n", " ")
                if not isinstance(exc, (ValueError, OSError, DozerlabError)):
                    message = f"{type(exc).__name__}: {message}"
                print(f"DAMAGED {path}: {message}", file=out)
            else:
                tally.fine += 1
    return tally


def _verify(args: argparse.Namespace) -> int:
    tally = verify([Path(p) for p in args.paths])
    checked = tally.fine + len(tally.damaged) + len(tally.unchecked)
    summary = {
        "checked": checked,
        "whole": tally.fine,
        "damaged": len(tally.damaged),
        "without checksums": len(tally.unchecked),
        "other files (not checked)": tally.other,
    }
    print("verify: " + ", ".join(f"{v} {k}" for k, v in summary.items()))
    if tally.ok:
        return 0
    print(
        "verify: re-run the jobs that wrote the artifacts named above (delete them and re-run "
        "the workflow), or copy them again",
        file=sys.stderr,
    )
    return 1
