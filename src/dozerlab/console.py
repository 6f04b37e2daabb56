"""The workflow's console: one line when a job starts, one when it ends with the progress, and
a closing summary; no shell commands, reasons or resource lists.

Snakemake prints every job's inputs, reason and shell command (the workflow passes each command
its config as inline JSON, up to 2 KB a line), so the progress of a sweep is lost in its output.
The Snakefile calls :func:`install` in the Snakemake process: it replaces Snakemake's console
handler with one that writes::

    23:01:07  start  simulate scenario=hill speed=1.0 depth=0.04  (job 9)
    23:01:31  done   simulate scenario=hill speed=1.0 depth=0.04  (24 s)  [5/37, 14%]
    23:01:31  FAILED train model=unet  (job 12): see logs/train/unet.log
        (the last lines of that log)

and a :class:`JobClock` on the same logger adds up the jobs' time by rule for the closing
summary and the parent MLflow run: where a sweep's time went, and how busy its cores were.

Snakemake's own log (``.snakemake/log/*.snakemake.log``, named at the end of the run) keeps
everything its console would have said, shell commands included; each job's output is in the
rule's ``log:`` file. Dry runs (``-n``) and ``--verbose`` keep Snakemake's console.
"""

from __future__ import annotations

import logging
import re
import sys
import time
from collections import Counter
from collections.abc import Mapping
from typing import Any, TextIO

#: Snakemake's chatter that says nothing a person following the sweep needs (its log keeps it).
QUIET_MESSAGES = (
    "Select jobs to execute",
    "Execute ",
    "Using shell:",
    "Rules claiming more threads",
    "Assuming unrestricted shared filesystem",
)
#: A failed shell command as Python words it: the command is the rule's, config JSON and all.
FAILED_COMMAND = re.compile(r"Command '.*' returned non-zero", re.DOTALL)
#: Lines of a failed job's log shown under its FAILED line (its error is at the end).
LOG_TAIL_LINES = 3
#: A rule whose jobs took less (s) took no time worth a line: the target rule's instant job.
INSTANT_S = 0.5


def _event(record: logging.LogRecord) -> str:
    """The record's Snakemake log event (``job_info``, ``progress``, …), "" for plain messages."""
    event = getattr(record, "event", None)
    return str(event) if event is not None else ""


def job_label(rule: str, wildcards: Mapping[str, Any] | None) -> str:
    """``rule k=v k=v``: a job as one short phrase."""
    return " ".join([rule, *(f"{k}={v}" for k, v in (wildcards or {}).items())])


def plan_line(stats: Mapping[str, int]) -> str:
    """Snakemake's job-count table as one line: ``37 jobs: bed 1, trajectory 6, …``."""
    rules = {k: v for k, v in stats.items() if k != "total"}
    total = stats.get("total", sum(rules.values()))
    return f"{total} jobs: " + ", ".join(f"{k} {v}" for k, v in rules.items())


def log_tail(path: str, lines: int = LOG_TAIL_LINES, width: int = 300) -> list[str]:
    """The last ``lines`` non-empty lines of the log at ``path``, each cut to ``width``
    characters; none if it cannot be read."""
    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            f.seek(max(0, f.tell() - 16384))
            text = f.read().decode("utf-8", "replace")
    except OSError:
        return []
    kept = [line.rstrip()[:width] for line in text.splitlines() if line.strip()]
    return kept[-lines:]


class ConsoleFormatter(logging.Formatter):
    """Snakemake's log records as the console lines of the module docstring.

    A job's end (``job_finished``) is held until the ``progress`` record Snakemake logs right
    after it, and printed with it as one line. Records this console does not shorten go through
    ``fallback`` (Snakemake's own formatter); "" drops a record.
    """

    def __init__(self, fallback: logging.Formatter | None = None) -> None:
        super().__init__()
        self.fallback = fallback or logging.Formatter()
        self.jobs: dict[int, tuple[str, float]] = {}  # job id: (label, start time)
        self.finished: list[str] = []

    def format(self, record: logging.LogRecord) -> str:
        event = _event(record)
        extra: dict[str, Any] = vars(record)  # the fields Snakemake logs with each event
        stamp = time.strftime("%H:%M:%S", time.localtime(record.created))
        if event == "job_info":
            label = job_label(str(extra["rule_name"]), extra.get("wildcards"))
            self.jobs[int(extra["jobid"])] = (label, record.created)
            return f"{stamp}  start  {label}  (job {extra['jobid']})"
        if event == "job_finished":
            job = int(extra["job_id"])
            label, began = self.jobs.pop(job, (f"job {job}", None))
            took = f"  ({record.created - began:.0f} s)" if began is not None else ""
            self.finished.append(f"{stamp}  done   {label}{took}")
            return ""
        if event == "progress":
            done, total = int(extra["done"]), int(extra["total"])
            share = f"[{done}/{total}, {100 * done / max(total, 1):.0f}%]"
            lines, self.finished = self.finished or [f"{stamp}  {done} of {total} jobs done"], []
            lines[-1] += f"  {share}"
            return "\n".join(lines)
        if event == "job_error":
            job = int(extra["jobid"])
            label = self.jobs.pop(job, (job_label(str(extra["rule_name"]), None), 0.0))[0]
            logs = [str(p) for p in extra.get("log") or []]
            why = f" ({extra['rule_msg']})" if extra.get("rule_msg") else ""
            head = f"{stamp}  FAILED {label}  (job {job}){why}: see {', '.join(logs) or 'the Snakemake log'}"
            return "\n".join([head, *(f"    {line}" for p in logs for line in log_tail(p))])
        if event == "run_info" and isinstance(extra.get("stats"), Mapping):
            return plan_line(extra["stats"])
        if event in ("shellcmd", "job_started", "workflow_started", "resources_info"):
            return ""
        text = self.fallback.format(record)
        if not event and text.startswith(QUIET_MESSAGES):
            return ""
        return FAILED_COMMAND.sub(
            "The job's command (in the Snakemake log) returned non-zero", text
        )


class JobClock(logging.Handler):
    """The jobs' time by rule, from Snakemake's log records: a job runs from its ``job_info``
    (started, or submitted to a cluster) to its ``job_finished``, and takes its ``threads`` of
    the cores Snakemake was given (``resources_info``). Jobs that fail are not counted. Add it
    to Snakemake's logger; it writes nothing."""

    def __init__(self) -> None:
        super().__init__()
        self.running: dict[int, tuple[str, float, int]] = {}  # job id: (rule, start, threads)
        self.seconds: dict[str, float] = {}
        self.jobs: Counter[str] = Counter()
        self.thread_seconds = 0.0
        self.cores: int | None = None

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self._count(record)
        except Exception:  # logging's contract: report, never raise into the workflow
            self.handleError(record)

    def _count(self, record: logging.LogRecord) -> None:
        event = _event(record)
        extra: dict[str, Any] = vars(record)
        if event == "job_info":
            threads = extra.get("threads")
            self.running[int(extra["jobid"])] = (
                str(extra["rule_name"]),
                record.created,
                int(threads) if isinstance(threads, int) and threads > 0 else 1,
            )
        elif event == "job_finished" and int(extra["job_id"]) in self.running:
            rule, began, threads = self.running.pop(int(extra["job_id"]))
            self.seconds[rule] = self.seconds.get(rule, 0.0) + record.created - began
            self.jobs[rule] += 1
            self.thread_seconds += (record.created - began) * threads
        elif event == "job_error":
            self.running.pop(int(extra["jobid"]), None)
        elif event == "resources_info" and isinstance(extra.get("cores"), int):
            self.cores = int(extra["cores"])

    def metrics(self) -> dict[str, float]:
        """``job_seconds/<rule>`` (s, the rule's jobs added up; not a rule of instant jobs
        such as the target rule) and ``job_seconds_total`` (beside the parent run's
        ``wall_seconds``); none before a job has finished."""
        if not self.jobs:
            return {}
        out = {f"job_seconds/{rule}": s for rule, s in self._timed()}
        return out | {"job_seconds_total": sum(self.seconds.values())}

    def _timed(self) -> list[tuple[str, float]]:
        """(rule, seconds), the largest first, without the rules whose jobs took no time."""
        ranked = sorted(self.seconds.items(), key=lambda kv: -kv[1])
        return [(rule, s) for rule, s in ranked if s >= INSTANT_S]

    def summary(self, wall_s: float) -> str | None:
        """One line for the closing summary: the job time, on how many cores in ``wall_s``
        seconds and how busy they were, then each rule's share, the largest first; None
        before a job has finished."""
        if not self.jobs:
            return None
        total = sum(self.seconds.values())
        head = f"  jobs      {total:.0f} s of job time"
        if self.cores and wall_s > 0:
            busy = self.thread_seconds / (self.cores * wall_s)
            head += f" on {self.cores} core{'s' * (self.cores > 1)} ({100 * busy:.0f} % busy)"
        rules = ", ".join(f"{rule} {s:.0f} s ({self.jobs[rule]})" for rule, s in self._timed())
        return f"{head}, by rule (jobs): {rules}"


class ConsoleHandler(logging.StreamHandler):
    """Writes what :class:`ConsoleFormatter` makes of a record, nothing for ""."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
            if text:
                self.stream.write(text + self.terminator)
                self.flush()
        except Exception:  # logging's contract: report, never raise into the workflow
            self.handleError(record)


def install(
    logger: logging.Logger, console: type[logging.Handler], stream: TextIO | None = None
) -> bool:
    """Replace Snakemake's console handler on ``logger`` (of class ``console``, Snakemake's
    ``ColorizingTextHandler``: the Snakefile names it, so the package needs no Snakemake) by a
    :class:`ConsoleHandler` writing to ``stream`` (default stderr); return whether there was
    one to replace.

    The replaced handler's filters (Snakemake's ``--quiet`` choices) stay; its file handler
    (``.snakemake/log``) and the handlers of logger plugins are left as they are. A dry run
    (``-n``) or ``--verbose`` keeps Snakemake's console: its filter says so (the workflow's own
    ``dryrun`` is not known yet when the Snakefile is read).
    """

    def wanted(handler: logging.Handler) -> bool:
        says = [getattr(f, k, False) for f in handler.filters for k in ("dryrun", "verbose")]
        return isinstance(handler, console) and not any(says)

    found = [h for h in logger.handlers if wanted(h)]
    for old in found:
        new = ConsoleHandler(stream or sys.stderr)
        new.setFormatter(ConsoleFormatter(old.formatter))
        for flt in old.filters:
            new.addFilter(flt)
        new.setLevel(old.level)
        logger.removeHandler(old)
        logger.addHandler(new)
    return bool(found)
