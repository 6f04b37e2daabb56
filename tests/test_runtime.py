"""The process-level settings: the thread budget, atomic outputs that replace only what the same
kind of command wrote, and jobs that stop with their workflow."""

import gc
import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from dozerlab.runtime import (
    FIGURE,
    FOLDER_MARK,
    DozerlabError,
    OutputExistsError,
    OutputKind,
    OutputPathError,
    atomic_output,
    check_name,
    check_output,
    die_with_workflow,
    freeze_heap,
    job_outputs,
    keep_freed_memory,
    marked_folder,
    marked_png,
    png_metadata,
    process_token,
    set_threads,
    thread_budget,
)


def test_freeze_heap_takes_the_live_objects_out_of_the_collectors_view():
    alive = [[i] for i in range(1000)]  # tracked containers, as a job's loaded modules are
    before = gc.get_freeze_count()
    freeze_heap()
    try:
        assert gc.get_freeze_count() >= before + len(alive)
        ids = {id(a) for a in alive}
        assert not any(id(o) in ids for o in gc.get_objects())
    finally:
        gc.unfreeze()


_REFAULTS = (
    "import resource, sys, numpy as np\n"
    "from dozerlab.runtime import keep_freed_memory\n"
    "kept = sys.argv[1] == 'kept' and keep_freed_memory()\n"
    "for i in range(3):\n"
    "    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
    "    a = np.ones(64 << 17)  # 64 MB, every page touched\n"
    "    del a\n"
    "print(kept, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)\n"
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_keep_freed_memory_lets_a_freed_block_serve_the_next_one_without_faulting_it_in():
    def faults(mode: str) -> tuple[str, int]:
        out = subprocess.run(
            [sys.executable, "-c", _REFAULTS, mode], check=True, capture_output=True, text=True
        ).stdout.split()
        return out[0], int(out[1])

    # mapped afresh: at least a fault per page, a 2 MB page where the kernel makes huge pages
    kept, refaults = faults("default")
    assert kept == "False" and refaults >= (64 << 20) // (2 << 20)
    kept, refaults = faults("kept")
    assert kept == "True" and refaults < 16  # the freed block again, its pages in
    assert keep_freed_memory() is True  # and again in this process: the same settings


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


TEXT = OutputKind("a test text file", lambda p: p.is_file() and p.read_text().startswith("ours"))


def write(out, text="ours", during=lambda: None):
    """Write ``text`` through atomic_output, calling ``during()`` before the block ends."""
    with atomic_output(out, TEXT) as tmp:
        tmp.write_text(text)
        during()


def killed():
    raise RuntimeError("killed")


def test_a_new_output_appears_only_on_success(tmp_path):
    out = tmp_path / "sub" / "out.txt"
    with pytest.raises(RuntimeError):
        write(out, "ours, half", during=killed)
    assert not out.exists() and not list(out.parent.iterdir())
    write(out, "ours, whole")
    assert out.read_text() == "ours, whole"


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


def test_an_output_of_the_same_kind_is_replaced(tmp_path):
    out = tmp_path / "out.txt"
    out.write_text("ours, old")
    write(out, "ours, new")
    assert out.read_text() == "ours, new"


@pytest.mark.parametrize("foreign", ["dir", "file", "symlink"])
def test_anything_else_is_refused_and_left_untouched(tmp_path, foreign):
    out = tmp_path / "out.txt"
    keep = tmp_path / "keep.txt"
    keep.write_text("a user's data")
    if foreign == "dir":
        out.mkdir()
        (out / "thesis.tex").write_text("years of work")
    elif foreign == "file":
        out.write_text("a user's data")
    else:
        out.symlink_to(keep)
    with pytest.raises(
        OutputExistsError, match=rf"refusing to replace {out}.*not a test text file"
    ):
        write(out)
    assert keep.read_text() == "a user's data"
    if foreign == "dir":
        assert (out / "thesis.tex").read_text() == "years of work"
    else:
        assert out.read_text() == "a user's data"
    assert not list(tmp_path.glob(".*tmp-*"))


def test_something_appearing_during_the_work_is_not_replaced(tmp_path):
    out = tmp_path / "out.txt"
    with pytest.raises(OutputExistsError):
        write(out, during=lambda: out.write_text("written meanwhile by someone else"))
    assert out.read_text() == "written meanwhile by someone else"


def test_without_a_kind_only_a_new_path_is_written(tmp_path):
    out = tmp_path / "out.txt"
    check_output(out, None)
    out.write_text("x")
    with pytest.raises(OutputExistsError, match="never replaced"):
        check_output(out, None)


def test_a_recogniser_that_fails_recognises_nothing(tmp_path):
    def broken(path):
        raise UnicodeDecodeError("utf-8", b"", 0, 1, "binary")

    out = tmp_path / "out.bin"
    out.write_bytes(b"\xff\xfe")
    with pytest.raises(OutputExistsError):
        check_output(out, OutputKind("anything", broken))


def test_a_file_in_the_way_of_the_directory_is_refused(tmp_path):
    (tmp_path / "plots").write_text("a file, not a directory")
    with pytest.raises(OutputExistsError, match="in the way"):
        write(tmp_path / "plots" / "a.txt")


def test_figures_are_marked_and_others_pngs_are_not_replaced(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    ours, theirs = tmp_path / "ours.png", tmp_path / "theirs.png"
    Figure().savefig(ours, format="png", metadata=png_metadata())
    Figure().savefig(theirs, format="png")
    check_output(ours, FIGURE)
    with pytest.raises(OutputExistsError, match="not a PNG figure written by dozerlab"):
        check_output(theirs, FIGURE)


def test_a_figure_marked_for_one_command_is_not_anothers(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    bed_plot, path_plot = marked_png("a bed figure", "bed-plot"), marked_png("a path", "path-plot")
    png = tmp_path / "fig.png"
    Figure().savefig(png, format="png", metadata=png_metadata(bed_plot.name))
    check_output(png, bed_plot)
    with pytest.raises(OutputExistsError, match="not a path"):
        check_output(png, path_plot)


FIGURES = marked_folder("a folder of test figures", "test-figures")


def write_folder(path, names=("a.png", "sub/b.png")):
    with atomic_output(path, FIGURES) as tmp:
        for name in names:
            (tmp / name).parent.mkdir(parents=True, exist_ok=True)
            (tmp / name).write_text(name)


def test_a_marked_folder_is_replaced_only_while_it_holds_only_what_it_lists(tmp_path):
    out = tmp_path / "figs"
    write_folder(out)
    assert FIGURES.recognise(out) and (out / FOLDER_MARK).is_file()
    (out / ".snakemake_timestamp").touch()  # as the workflow leaves a directory() output
    write_folder(out, ["c.png"])  # ours: replaced whole
    assert sorted(p.name for p in out.iterdir()) == [FOLDER_MARK, "c.png"]
    (out / "keep.txt").write_text("added by a user")
    with pytest.raises(OutputExistsError, match="not a folder of test figures"):
        write_folder(out)
    assert (out / "keep.txt").read_text() == "added by a user"


@pytest.mark.parametrize("folder", ["empty", "users", "another kind's"])
def test_a_folder_not_marked_as_this_kind_is_refused(tmp_path, folder):
    out = tmp_path / "figs"
    if folder == "another kind's":
        with atomic_output(out, marked_folder("other", "other-figures")) as tmp:
            tmp.mkdir()
    else:
        out.mkdir()
        if folder == "users":
            (out / "keep.txt").write_text("mine")
    with pytest.raises(OutputExistsError, match=f"refusing to replace {out}"):
        write_folder(out)


def test_a_failed_job_leaves_none_of_its_outputs_and_restores_the_earlier_ones(tmp_path):
    earlier = tmp_path / "a.txt"
    earlier.write_text("ours, earlier")
    new = tmp_path / "sub" / "deeper" / "b.txt"

    def job():
        with job_outputs(("--a", earlier, TEXT), ("--b", new, TEXT)):
            write(earlier, "ours, this run")
            write(new, "ours, this run")
            killed()

    with pytest.raises(RuntimeError):
        job()
    assert earlier.read_text() == "ours, earlier"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]  # no folder, temporary, kept copy


def test_a_job_that_succeeds_keeps_no_earlier_output(tmp_path):
    earlier = tmp_path / "a.txt"
    earlier.write_text("ours, earlier")
    with job_outputs(("--a", earlier, TEXT), ("--b", None, TEXT)):
        write(earlier, "ours, this run")
    assert earlier.read_text() == "ours, this run"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_every_output_is_checked_before_the_body_runs(tmp_path):
    (tmp_path / "file").write_text("in the way")
    ran = []
    with (
        pytest.raises(OutputPathError, match=r"\(--b\): .* is a file, not a folder"),
        job_outputs(("--a", tmp_path / "a.txt", TEXT), ("--b", tmp_path / "file" / "b", TEXT)),
    ):
        ran.append(True)
    assert not ran and sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_outputs_inside_each_other_are_refused(tmp_path):
    with (
        pytest.raises(OutputPathError, match="would overwrite each other"),
        job_outputs(("--out", tmp_path / "d", None), ("--plots", tmp_path / "d" / "p", None)),
    ):
        pass


@pytest.mark.parametrize("name", ["ridge", "unet-2", "speed~1.0", "a.b"])
def test_a_name_is_accepted(name):
    assert check_name(name, "--model") == name


@pytest.mark.parametrize(
    ("name", "why"),
    [
        ("", "is empty"),
        (".", "is not a name"),
        ("..", "is not a name"),
        ("../../victim", "holds a path separator"),
        ("/abs", "holds a path separator"),
        ("a\\b", "holds a path separator"),
        ("a\0b", "holds a NUL character"),
        ("x" * 256, "is longer than 255 bytes"),
    ],
)
def test_a_path_is_not_a_name(name, why):
    with pytest.raises(DozerlabError, match=f"--dynamics-model .* {why}"):
        check_name(name, "--dynamics-model")


WORKFLOW = """
import os, socket, subprocess, sys, time
os.environ["DOZERLAB_WORKFLOW_PID"] = str(os.getpid())
os.environ["DOZERLAB_WORKFLOW_HOST"] = socket.gethostname()
subprocess.Popen([sys.executable, "-c", sys.argv[1], sys.argv[2]], stderr=open(sys.argv[3], "w"))
time.sleep(120)
"""
JOB = """
import sys, time
from dozerlab.runtime import atomic_output, die_with_workflow
assert die_with_workflow(poll_s=0.1)
with atomic_output(sys.argv[1]) as tmp:
    tmp.write_text("half")
    time.sleep(120)
"""


def test_a_job_stops_when_its_snakemake_is_killed(tmp_path):
    """SIGKILL reaps no children: the job notices its workflow is gone and exits cleanly."""
    out, err = tmp_path / "out.txt", tmp_path / "job.err"
    workflow = subprocess.Popen([sys.executable, "-c", WORKFLOW, JOB, str(out), str(err)])
    try:
        deadline = time.monotonic() + 60
        while not (partial := list(tmp_path.glob(".out.txt.tmp-*"))):
            assert time.monotonic() < deadline and workflow.poll() is None, err.read_text()
            time.sleep(0.05)
        job_pid = int(partial[0].name.rsplit("-", 1)[1])
        os.kill(workflow.pid, signal.SIGKILL)
        workflow.wait()
        deadline = time.monotonic() + 10
        while process_token(job_pid) is not None:
            assert time.monotonic() < deadline, "the orphaned job runs on"
            time.sleep(0.05)
    finally:
        workflow.kill()
    assert (
        "snakemake process" in err.read_text() and "is gone; stopping this job" in err.read_text()
    )
    assert not out.exists() and not list(tmp_path.glob(".*tmp-*"))  # its temporary went with it


def test_a_job_without_a_workflow_is_not_watched(monkeypatch):
    monkeypatch.delenv("DOZERLAB_WORKFLOW_PID", raising=False)
    assert not die_with_workflow()
    monkeypatch.setenv("DOZERLAB_WORKFLOW_PID", str(os.getpid()))
    monkeypatch.setenv("DOZERLAB_WORKFLOW_HOST", "another-node")
    assert not die_with_workflow()


def test_temporaries_of_dead_writers_on_this_host_are_removed(tmp_path):
    host = socket.gethostname()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".out.txt.tmp-{host}-{dead.pid}"
    live = tmp_path / f".out.txt.tmp-{host}-{os.getppid()}"  # a writer still at work
    remote = tmp_path / f".out.txt.tmp-another-node-{dead.pid}"  # cannot be checked from here
    for p in (stale, live, remote):
        p.mkdir()
        (p / "part").write_text("x")
    write(tmp_path / "out.txt")
    assert not stale.exists() and live.exists() and remote.exists()
    assert (tmp_path / "out.txt").read_text() == "ours"
