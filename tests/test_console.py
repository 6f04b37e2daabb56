"""The workflow's console: one line per job start and end with the progress, no shell commands,
and Snakemake's file log left whole."""

import io
import logging

from snakemake.logging import ColorizingTextHandler
from snakemake_interface_logger_plugins.common import LogEvent

from dozerlab import console


def record(msg, **extra):
    rec = logging.LogRecord("snakemake.logging", logging.INFO, __file__, 1, msg, None, None)
    rec.__dict__.update(extra)
    return rec


def test_a_job_is_one_line_when_it_starts_and_one_with_the_progress_when_it_ends():
    fmt = console.ConsoleFormatter()
    wildcards = {"scenario": "hill", "speed": "1.0", "depth": "0.04"}
    start = record(
        "Rule: simulate",
        event=LogEvent.JOB_INFO,
        jobid=9,
        rule_name="simulate",
        wildcards=wildcards,
        rule_msg=None,
        reason="Missing output files: " + "x" * 3000,
    )
    line = fmt.format(start)
    assert line.endswith("start  simulate scenario=hill speed=1.0 depth=0.04  (job 9)")
    shell = record(
        "Shell command: python -m dozerlab simulate --config '{...}'", event=LogEvent.SHELLCMD
    )
    assert fmt.format(shell) == ""
    assert fmt.format(record("Finished jobid: 9", event=LogEvent.JOB_FINISHED, job_id=9)) == ""
    done = fmt.format(record(None, event=LogEvent.PROGRESS, done=5, total=37))
    assert "done   simulate scenario=hill speed=1.0 depth=0.04  (" in done
    assert done.endswith("[5/37, 14%]") and "\n" not in done


def test_the_plan_is_one_line_and_a_failure_names_its_log_and_shows_its_end(tmp_path):
    fmt = console.ConsoleFormatter()
    stats = {"bed": 1, "simulate": 6, "all": 1, "total": 8}
    plan = fmt.format(record("Job stats: ...", event=LogEvent.RUN_INFO, stats=stats))
    assert plan == "8 jobs: bed 1, simulate 6, all 1"
    info = {"jobid": 3, "rule_name": "train", "wildcards": {"model": "unet"}}
    fmt.format(record("", event=LogEvent.JOB_INFO, **info))
    log = tmp_path / "unet.log"
    log.write_text("epoch 1\n" * 50 + "dozerlab train: error: no such store 'x.zarr'\n\n")
    failed = fmt.format(
        record(
            "Error in rule train",
            event=LogEvent.JOB_ERROR,
            log=[str(log)],
            rule_msg=None,
            shellcmd="python -m dozerlab train " + "y" * 2000,
            **info,
        )
    ).splitlines()
    assert failed[0].endswith(f"FAILED train model=unet  (job 3): see {log}")
    assert failed[1:] == [
        "    epoch 1",
        "    epoch 1",
        "    dozerlab train: error: no such store 'x.zarr'",
    ]
    # Python's words for the failed command hold the whole command line: not on the console
    raised = (
        "RuleException:\nCalledProcessError in file x.smk:\nCommand 'python -m dozerlab "
        + "{" * 2000
    )
    said = fmt.format(record(raised + "' returned non-zero exit status 2."))
    assert len(said) < 200 and said.endswith("returned non-zero exit status 2.")
    assert fmt.format(record("Select jobs to execute...")) == ""
    nothing = "Nothing to be done (all requested files are present and up to date)."
    assert fmt.format(record(nothing)) == nothing


def test_install_replaces_the_console_handler_and_keeps_the_file_log(tmp_path):
    logger = logging.getLogger("test_console")
    logger.setLevel(logging.INFO)
    old = ColorizingTextHandler(stream=io.StringIO())
    file_handler = logging.FileHandler(tmp_path / "snakemake.log")
    logger.addHandler(old)
    logger.addHandler(file_handler)
    out = io.StringIO()
    try:
        assert console.install(logger, ColorizingTextHandler, out)
        assert old not in logger.handlers and file_handler in logger.handlers
        logger.info("Shell command: python -m dozerlab bed", extra={"event": LogEvent.SHELLCMD})
        logger.info("Building DAG of jobs...")
    finally:
        for h in list(logger.handlers):
            logger.removeHandler(h)
        file_handler.close()
    assert out.getvalue() == "Building DAG of jobs...\n"
    assert "Shell command: python -m dozerlab bed" in (tmp_path / "snakemake.log").read_text()
    assert not console.install(logging.getLogger("test_console_none"), ColorizingTextHandler)


def test_a_dry_run_keeps_snakemakes_console():
    from snakemake.logging import DefaultFilter

    logger = logging.getLogger("test_console_dry")
    old = ColorizingTextHandler(stream=io.StringIO())
    old.addFilter(DefaultFilter(None, False, False, True, True))  # dryrun
    logger.addHandler(old)
    try:
        assert not console.install(logger, ColorizingTextHandler) and old in logger.handlers
    finally:
        logger.removeHandler(old)


def test_the_job_clock_adds_up_each_rules_job_time_and_how_busy_the_cores_were():
    clock = console.JobClock()
    assert clock.summary(60.0) is None and clock.metrics() == {}

    def at(t, msg, **extra):
        rec = record(msg, **extra)
        rec.created = t
        clock.handle(rec)

    at(0.0, "Provided cores: 2", event=LogEvent.RESOURCES_INFO, cores=2)
    at(0.0, "", event=LogEvent.JOB_INFO, jobid=1, rule_name="simulate", threads=1)
    at(1.0, "", event=LogEvent.JOB_INFO, jobid=2, rule_name="simulate", threads=1)
    at(30.0, "", event=LogEvent.JOB_FINISHED, job_id=1)
    at(30.0, "", event=LogEvent.JOB_INFO, jobid=3, rule_name="train", threads=2)
    at(41.0, "", event=LogEvent.JOB_FINISHED, job_id=2)
    at(50.0, "", event=LogEvent.JOB_INFO, jobid=4, rule_name="train", threads=1)
    at(55.0, "", event=LogEvent.JOB_ERROR, jobid=4, rule_name="train")  # a failure is no time
    at(60.0, "", event=LogEvent.JOB_FINISHED, job_id=3)
    at(60.0, "", event=LogEvent.JOB_INFO, jobid=5, rule_name="all", threads=1)
    at(60.0, "", event=LogEvent.JOB_FINISHED, job_id=5)
    assert clock.metrics() == {
        "job_seconds/simulate": 70.0,
        "job_seconds/train": 30.0,
        "job_seconds_total": 100.0,
    }
    # 30 + 40 s on one thread and 30 s on two: 130 thread-seconds, 2 cores for 65 s
    assert clock.summary(65.0) == (
        "  jobs      100 s of job time on 2 cores (100 % busy), by rule (jobs): simulate 70 s (2), "
        "train 30 s (1)"
    )
