"""The process-level settings: thread budget and atomic outputs."""

import os
import subprocess
import sys

import pytest

from dozerlab.runtime import DozerlabError, atomic_output, set_threads, thread_budget


def test_set_threads_limits_numba_torch_and_blas_in_a_fresh_process():
    code = (
        "import os, numba, torch\n"
        "from dozerlab.runtime import set_threads\n"
        "n = set_threads(1)\n"
        "print(n, numba.get_num_threads(), torch.get_num_threads(), os.environ['OMP_NUM_THREADS'],"
        " os.environ['OPENBLAS_NUM_THREADS'])\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], check=True, capture_output=True, text=True
    ).stdout
    assert out.split() == ["1", "1", "1", "1", "1"]


def test_set_threads_sets_numba_pool_size_only_before_numba_starts():
    code = (
        "import os, sys\n"
        "from dozerlab.runtime import set_threads\n"
        "set_threads(1)\n"
        "print(os.environ.get('NUMBA_NUM_THREADS'), 'numba' in sys.modules)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    out = subprocess.run(
        [sys.executable, "-c", code], check=True, capture_output=True, text=True, env=env
    ).stdout
    assert out.split() == ["1", "True"]


def test_set_threads_never_asks_for_more_than_numba_has():
    import numba

    assert set_threads(10_000) == numba.config.NUMBA_NUM_THREADS


@pytest.mark.parametrize("n", [0, -2])
def test_set_threads_refuses_less_than_one(n):
    with pytest.raises(ValueError, match="threads must be >= 1"):
        set_threads(n)


def test_thread_budget_reads_omp_num_threads(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert thread_budget() == 3
    for bad in ("", "zero", "0"):
        monkeypatch.setenv("OMP_NUM_THREADS", bad)
        assert thread_budget() == len(os.sched_getaffinity(0))


def test_atomic_output_file_appears_only_on_success(tmp_path):
    target = tmp_path / "sub" / "out.txt"
    with atomic_output(target) as tmp:
        assert tmp.parent == target.parent and tmp != target
        tmp.write_text("done")
        assert not target.exists()
    assert target.read_text() == "done"
    assert list(target.parent.iterdir()) == [target]


def test_atomic_output_directory_store(tmp_path):
    target = tmp_path / "store.zarr"
    with atomic_output(target) as tmp:
        (tmp / "group").mkdir(parents=True)
        (tmp / "group" / "zarr.json").write_text("{}")
    assert (target / "group" / "zarr.json").read_text() == "{}"


def _write_then_fail(target, exc: BaseException) -> None:
    with atomic_output(target) as tmp:
        (tmp / "data").mkdir(parents=True)
        (tmp / "data" / "chunk").write_bytes(b"half written")
        raise exc


@pytest.mark.parametrize("exc", [DozerlabError("diverged"), KeyboardInterrupt()])
def test_atomic_output_failure_leaves_no_output_and_no_temporary(tmp_path, exc):
    with pytest.raises(type(exc)):
        _write_then_fail(tmp_path / "store.zarr", exc)
    assert list(tmp_path.iterdir()) == []
