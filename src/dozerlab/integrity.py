"""Reading back what the package wrote, every byte checked: ``.npz`` files, JSON documents and
files recorded by their SHA-256.

A loader that reads a damaged file (a copy cut short, a flipped bit on a disk or a network)
must refuse it naming the file, never hand on changed numbers and never end in a library's
traceback. Each kind of file has one checker here or next to its format, which its loader and
``dozerlab verify`` both call:

- ``.npz`` (beds, final states, World files): a zip archive with a CRC-32 of every member,
  all checked (:func:`read_npz`) before any array is used. A CRC-32 detects every error burst of
  up to 32 bits and all but 1 in 4·10⁹ others: enough for copies and disks. It does not stop a
  deliberate edit, nor would an unkeyed SHA-256 stored beside the data (it is recomputed as
  easily), so the files keep their format and older ones stay readable.
- model files: their SHA-256 recorded at saving (:func:`sha256_file`), compared on loading;
  a trajectory CSV's SHA-256 is its last line (``dozerlab.scenarios.trajectory``).
- JSON: parsed or refused naming the file (:func:`read_json`).
"""

from __future__ import annotations

import hashlib
import json
import zipfile
import zlib
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.runtime import DozerlabError


class DamagedFileError(DozerlabError, ValueError):
    """A file that does not hold what was written to it (cut short, changed bytes, NaN where a
    finite number was written); the message names the file and what is wrong."""


def read_npz(path: str | Path, what: str, keys: Collection[str]) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path``, after every member's CRC-32 is checked.

    ``what`` names the kind of file in messages ("a dozerlab bed file"), ``keys`` are the arrays
    it must hold. Raises :class:`FileNotFoundError` when ``path`` is no file, and
    :class:`DamagedFileError` naming the file for a damaged archive, a member failing its CRC-32
    or a missing array. Never unpickles (``allow_pickle=False``).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()
            if bad is not None:
                raise DamagedFileError(
                    f"{path} is damaged: its array {bad} fails its CRC-32 check (changed bytes); "
                    "re-run the job that wrote it, or copy it again"
                )
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except DamagedFileError:
        raise
    except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, KeyError) as exc:
        raise DamagedFileError(
            f"{path} is damaged or not {what} (cut short or changed bytes: {exc}); re-run the "
            "job that wrote it, or copy it again"
        ) from exc
    missing = [k for k in keys if k not in arrays]
    if missing:
        raise DamagedFileError(f"{path} is not {what}: it lacks the arrays {missing}")
    return arrays


def require_finite(
    path: str | Path, arrays: Mapping[str, np.ndarray], names: Collection[str]
) -> None:
    """Refuse NaN/inf in the arrays ``names`` of a file at ``path`` (:class:`DamagedFileError`
    naming the file, the array and the first row)."""
    for name in names:
        values = np.asarray(arrays[name])
        if values.dtype.kind in "fc":
            bad = np.argwhere(~np.isfinite(values))
            if bad.size:
                row = f", first in row {bad[0][0]}" if values.ndim else ""
                raise DamagedFileError(f"{path}: '{name}' holds {len(bad)} NaN/inf value(s){row}")


def sha256_file(path: str | Path) -> str:
    """The SHA-256 of a file's bytes, as hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def sha256_json(doc: Any) -> str:
    """The SHA-256 of a JSON document in canonical form (key order and whitespace do not count),
    as hex: a document can record its own digest beside its content."""
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode()).hexdigest()


def read_json(path: str | Path, what: str) -> Any:
    """The JSON document at ``path``; :class:`DamagedFileError` naming the file and the cause
    when it is unreadable or not JSON (``what`` names the kind of file)."""
    path = Path(path)
    try:
        return json.loads(path.read_bytes())
    except FileNotFoundError:
        raise
    except (OSError, ValueError) as exc:
        raise DamagedFileError(f"{path} is not valid JSON ({what}): {exc}") from exc
