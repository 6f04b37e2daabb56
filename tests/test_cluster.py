"""What the workflow's jobs ask of a SLURM cluster: the SLURM profile with the configs fits a
small node, a config that asks too much is refused with the field to lower, and the rules really
take their resources from the config."""

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from dozerlab import cluster
from dozerlab.config import load_config

REPO = Path(__file__).resolve().parents[1]
PROFILE = yaml.safe_load((REPO / "profiles" / "slurm" / "config.yaml").read_text())

#: A small compute node: 2 CPUs and 4 GB, in the cluster's only (default) partition.
SMALL = [
    cluster.Node("small", cpus=2, mem_mb=4000, partitions=("batch",), default_partition="batch")
]


def layered(*paths: Path) -> dict:
    """Config files laid over each other as Snakemake does (later files win, field by field)."""
    doc: dict = {}

    def merge(into: dict, new: dict) -> None:
        for key, value in new.items():
            if isinstance(value, dict) and isinstance(into.get(key), dict):
                merge(into[key], value)
            else:
                into[key] = value

    for path in paths:
        merge(doc, yaml.safe_load(path.read_text()) or {})
    return load_config(doc)


def profile_requests(config: dict) -> list[cluster.Request]:
    """The requests of every rule under the SLURM profile: the config's, with the profile's
    set-threads / set-resources (if any) applied over them, as Snakemake applies them."""
    threads = PROFILE.get("set-threads", {})
    resources = PROFILE.get("set-resources", {})
    return [
        cluster.Request(
            r.job,
            int(threads.get(r.job, r.threads)),
            int(resources.get(r.job, {}).get("mem_mb", r.mem_mb)),
            r.partition,
        )
        for r in cluster.config_requests(config)
    ]


@pytest.mark.parametrize(
    "configfiles",
    [["config.yaml"], ["config.yaml", "quick.yaml"]],
    ids=["default", "quick"],
)
def test_the_profile_never_asks_more_than_a_small_node_offers(configfiles):
    config = layered(*(REPO / "config" / name for name in configfiles))
    requests = profile_requests(config)
    assert {r.job for r in requests} == set(cluster.RULES)
    cluster.check_fit(requests, SMALL)
    # Rules without their own resources get the profile's defaults: those fit too.
    defaults = PROFILE["default-resources"]
    cluster.check_fit([cluster.Request("other", 1, int(defaults["mem_mb"]))], SMALL)


def test_a_config_that_asks_too_much_is_refused_naming_job_field_and_node():
    config = load_config({"threads": {"bed": 8}, "cluster": {"mem_mb": {"train": 32000}}})
    with pytest.raises(cluster.ClusterFitError) as err:
        cluster.check_fit(cluster.config_requests(config), SMALL)
    message = str(err.value)
    assert "job bed asks 8 threads and 2000 MB" in message
    assert "job train asks 2 threads and 32000 MB" in message
    assert "at most 2 CPUs, 4000 MB a node" in message
    assert "threads.<rule> / cluster.mem_mb.<rule>" in message
    assert "simulate" not in message  # the jobs that fit are not blamed


def test_a_job_must_fit_one_node_not_the_sum_of_two():
    nodes = [
        cluster.Node("cpu", cpus=8, mem_mb=2000, partitions=("p",), default_partition="p"),
        cluster.Node("mem", cpus=1, mem_mb=64000, partitions=("p",), default_partition="p"),
    ]
    cluster.check_fit([cluster.Request("a", 8, 2000), cluster.Request("b", 1, 64000)], nodes)
    assert cluster.unfit([cluster.Request("c", 8, 64000)], nodes) == [
        "job c asks 8 threads and 64000 MB, but no node of partition 'p' has both "
        "(at most 8 CPUs, 64000 MB a node)"
    ]


def test_requests_are_checked_against_their_own_partition():
    nodes = cluster.parse_sinfo("n1|2|4000|small*\nn2|64|512000|big\n")
    cluster.check_fit([cluster.Request("train", 32, 100000, "big")], nodes)
    assert len(cluster.unfit([cluster.Request("train", 32, 100000)], nodes)) == 1  # default: small
    assert cluster.unfit([cluster.Request("train", 1, 100, "gpu")], nodes) == [
        "job train: partition 'gpu' has no nodes (partitions: big, small)"
    ]


def test_parse_sinfo_reads_nodes_partitions_and_the_default():
    nodes = cluster.parse_sinfo("vm|2|21694|dozerlab*\nvm|2|21694|long\nbig|64|512000+|long\n\n")
    assert nodes == [
        cluster.Node("vm", 2, 21694, ("dozerlab", "long"), "dozerlab"),
        cluster.Node("big", 64, 512000, ("long",), "dozerlab"),
    ]
    with pytest.raises(ValueError, match=r"NODE\|CPUS\|MEMORY\|PARTITION"):
        cluster.parse_sinfo("vm 2 21694 dozerlab*")


def test_job_resources_name_account_and_partition_only_when_set():
    config = load_config(None)
    assert cluster.job_resources(config, "train") == {"mem_mb": 4000, "runtime": 120}
    config = load_config({"cluster": {"account": "lab", "partition": "gpu"}})
    assert cluster.job_resources(config, "simulate") == {
        "mem_mb": 2000,
        "runtime": 120,
        "slurm_account": "lab",
        "slurm_partition": "gpu",
    }
    assert cluster.job_threads(config, "bed") == config["threads"]["bed"]
    assert cluster.job_threads(config, "report") == config["threads"]["report"] == 2
    assert cluster.job_threads(config, "validate") == 1


@pytest.mark.parametrize(
    "base",
    [pytest.param("config.yaml", marks=pytest.mark.slow), "quick.yaml"],  # a dry run each
)
def test_the_rules_take_memory_time_and_partition_from_a_config_overlay(tmp_path, base):
    """A dry run shows what each job would ask: an overlay raises one field, the rest stay."""
    overlay = tmp_path / "cluster.yaml"
    overlay.write_text("cluster: {partition: big, mem_mb: {train: 12345}, runtime: {bed: 77}}\n")
    cmd = [sys.executable, "-m", "snakemake", "-n", "--cores", "2", "-s", str(REPO / "Snakefile"),
           "--directory", str(tmp_path), "--configfile", str(REPO / "config" / base),
           str(overlay)]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    blocks = {}
    for block in done.stdout.split("\nrule ")[1:]:
        rule = block.split(":", 1)[0]
        line = next(x for x in block.splitlines() if x.strip().startswith("resources:"))
        blocks.setdefault(rule, line)
    del blocks["all"]  # a local rule, no job of its own
    assert "mem_mb=12345" in blocks["train"] and "runtime=120" in blocks["train"]
    assert "mem_mb=2000" in blocks["bed"] and "runtime=77" in blocks["bed"]
    assert "mem_mb=1000" in blocks["trajectory"]
    assert all("slurm_partition=big" in line for line in blocks.values())
    assert all("slurm_account" not in line for line in blocks.values())
