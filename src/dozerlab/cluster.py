"""What the workflow's jobs ask of a SLURM cluster, and whether its nodes can give it.

A job that asks more threads or memory than any node of its partition has is accepted by
``sbatch`` on clusters without ``EnforcePartLimits`` and then pends forever with no message. The
workflow therefore compares every job's request with the nodes ``sinfo`` reports before it
submits anything (the Snakefile's ``onstart``) and refuses, naming the job, the config field and
what the largest node offers.
"""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

#: The rules that run as cluster jobs; each has ``cluster.mem_mb`` / ``cluster.runtime`` fields.
RULES = (
    "bed",
    "trajectory",
    "simulate",
    "twin",
    "train",
    "validate",
    "train_dynamics",
    "validate_dynamics",
    "reduce",
    "reduce_training_points",
    "train_loop_force",
    "compare_reduced",
    "report",
    "plot_fields",
)

#: Where each rule's threads come from: a field of the config's ``threads`` section, or 1.
THREADED = {
    "bed": "bed",
    "simulate": "simulate",
    "twin": "simulate",  # NDEM's run of the point, at its threads
    "train": "train",
    "train_dynamics": "dynamics",
    "reduce": "simulate",  # the NDEM run's threads: the speed-up compares the two at equal threads
    "reduce_training_points": "simulate",
    "train_loop_force": "train",
    "report": "report",
}


class ClusterFitError(ValueError):
    """A job asks more than every node of its partition offers."""


@dataclass(frozen=True)
class Node:
    """One SLURM node: ``cpus`` schedulable CPUs, ``mem_mb`` memory in MB, its partitions."""

    name: str
    cpus: int
    mem_mb: int
    partitions: tuple[str, ...]
    default_partition: str = ""


@dataclass(frozen=True)
class Request:
    """What one job asks: ``threads`` CPUs and ``mem_mb`` MB on one node of ``partition``.

    An empty ``partition`` means the cluster's default partition.
    """

    job: str
    threads: int
    mem_mb: int
    partition: str = ""


def job_resources(config: Mapping[str, Any], rule: str) -> dict[str, int | str]:
    """A rule's Snakemake ``resources``: ``mem_mb`` (MB), ``runtime`` (minutes) and, when the
    config names them, ``slurm_account`` and ``slurm_partition``.

    ``config`` is a validated config (every default filled in).
    """
    section = config["cluster"]
    out: dict[str, int | str] = {
        "mem_mb": section["mem_mb"][rule],
        "runtime": section["runtime"][rule],
    }
    if section["account"]:
        out["slurm_account"] = section["account"]
    if section["partition"]:
        out["slurm_partition"] = section["partition"]
    return out


def job_threads(config: Mapping[str, Any], rule: str) -> int:
    """Threads of a rule's jobs: the config's ``threads.<rule>``, or 1 for single-threaded rules."""
    return int(config["threads"][THREADED[rule]]) if rule in THREADED else 1


def config_requests(config: Mapping[str, Any]) -> list[Request]:
    """The request of every rule's jobs under a validated config."""
    partition = config["cluster"]["partition"]
    return [
        Request(rule, job_threads(config, rule), int(config["cluster"]["mem_mb"][rule]), partition)
        for rule in RULES
    ]


def parse_sinfo(text: str) -> list[Node]:
    """Nodes from ``sinfo --noheader --Node --format '%N|%c|%m|%P'`` output.

    sinfo prints one line per node and partition, and marks the default partition with ``*``.
    """
    cpus: dict[str, int] = {}
    mem: dict[str, int] = {}
    parts: dict[str, list[str]] = {}
    default = ""
    for line in text.splitlines():
        if not line.strip():
            continue
        fields = line.strip().split("|")
        if len(fields) != 4:
            raise ValueError(f"unexpected sinfo line (want NODE|CPUS|MEMORY|PARTITION): {line!r}")
        name, ncpu, memory, partition = fields
        if partition.endswith("*"):
            partition = partition[:-1]
            default = partition
        cpus[name] = int(ncpu)
        mem[name] = int(memory.rstrip("+"))
        parts.setdefault(name, []).append(partition)
    return [Node(n, cpus[n], mem[n], tuple(parts[n]), default) for n in cpus]


def slurm_nodes() -> list[Node]:
    """The nodes of the SLURM cluster this machine submits to (``sinfo``; ``SLURM_CONF`` applies)."""
    done = subprocess.run(
        ["sinfo", "--noheader", "--Node", "--format", "%N|%c|%m|%P"],
        capture_output=True,
        text=True,
        check=False,
        env=os.environ,
    )
    if done.returncode != 0:
        raise RuntimeError(f"sinfo failed ({done.returncode}): {done.stderr.strip()}")
    return parse_sinfo(done.stdout)


def unfit(requests: Iterable[Request], nodes: list[Node]) -> list[str]:
    """One message for each request that no single node of its partition can hold."""
    problems = []
    for req in requests:
        partition = req.partition or next((n.default_partition for n in nodes), "")
        members = [n for n in nodes if partition in n.partitions]
        if not members:
            known = sorted({p for n in nodes for p in n.partitions})
            problems.append(
                f"job {req.job}: partition '{partition}' has no nodes (partitions: {', '.join(known)})"
            )
            continue
        if any(n.cpus >= req.threads and n.mem_mb >= req.mem_mb for n in members):
            continue
        most_cpus = max(n.cpus for n in members)
        most_mem = max(n.mem_mb for n in members)
        problems.append(
            f"job {req.job} asks {req.threads} threads and {req.mem_mb} MB, but no node of "
            f"partition '{partition}' has both (at most {most_cpus} CPUs, {most_mem} MB a node)"
        )
    return problems


def check_fit(requests: Iterable[Request], nodes: list[Node]) -> None:
    """Raise :class:`ClusterFitError` listing every request no node of its partition can hold.

    Such a job would be accepted by sbatch and pend forever; the message names what to lower.
    """
    problems = unfit(requests, nodes)
    if problems:
        raise ClusterFitError(
            "refusing to submit: "
            + "; ".join(problems)
            + ". Lower the config's threads.<rule> / cluster.mem_mb.<rule> (or --set-threads /"
            " --set-resources), or choose a partition with larger nodes (cluster.partition)."
        )
