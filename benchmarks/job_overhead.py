"""A workflow job's cost outside its own work, its MLflow run spooled (as the workflow runs jobs)
against opened by the job itself (as before), side by side.

    python benchmarks/job_overhead.py --workdir DIR [--configfile config/quick.yaml] [--repeat 3]
        [--rules RULE ...] [--against OLD]

DIR is a folder where that config's sweep has run (its ``results/`` are read, never written).
The script takes one command line of each of the rules ``simulate``, ``validate`` and
``validate_dynamics`` from Snakemake itself (``snakemake -n -p --forcerun RULE``),
points their outputs into a temporary folder and runs each ``--repeat`` times, alternately with a
spool (``DOZERLAB_MLFLOW_SPOOL`` and a parent run id: the run is written to disk, no MLflow) and
without (the job imports MLflow, opens a temporary SQLite store and logs there). It prints each
job's wall time per mode and, for simulate, the overhead: the wall time less the stepping loop
(the store's ``wall_time_s``), what issue 14's ≤ 3 s target measures. (Rule ``reduce`` runs a
model's held-out points in one job, each point's share of it in ``results/reduced/{model}.json``,
``job_wall_s``.) With
``--against OLD`` each run is followed by the same run on the checkout OLD's code
(``PYTHONPATH=OLD/src``; ``--modes live`` for one from before the spool), side by side.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RULES = ("simulate", "validate", "validate_dynamics")
#: The options naming a job's outputs, pointed into the temporary folder.
OUTPUTS = ("--out", "--state", "--plots")


def command(workdir: Path, configfile: str, rule: str) -> list[str]:
    """The first command line Snakemake would run for ``rule``, without its log redirection."""
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "snakemake",
            "-n",
            "-p",
            "--forcerun",
            rule,
            "--configfile",
            configfile,
            "--cores",
            "2",
        ],
        cwd=workdir,
        capture_output=True,
        text=True,
        check=True,
        env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"},  # for the jobs alone
    )
    marker = f"dozerlab {rule.replace('_', '-')} "
    for line in (done.stdout + done.stderr).splitlines():
        if marker in line:
            cmd = line.split("Shell command:", 1)[-1].strip()
            return shlex.split(re.sub(r"\s*>\s*\S+\s+2>&1\s*$", "", cmd))
    raise SystemExit(f"no {rule} command in Snakemake's dry run in {workdir}")


def retarget(cmd: list[str], tmp: Path) -> tuple[list[str], dict[str, str]]:
    """The command with its outputs in ``tmp`` and its leading VAR=value words as env."""
    env = {}
    while "=" in cmd[0] and not cmd[0].startswith("-"):
        key, value = cmd.pop(0).split("=", 1)
        env[key] = value
    out = list(cmd)
    for i, word in enumerate(out[:-1]):
        if word in OUTPUTS:
            out[i + 1] = str(tmp / f"{word[2:]}{Path(out[i + 1]).suffix}")
    return out, env


def run_once(cmd: list[str], env: dict[str, str], workdir: Path, tmp: Path) -> float:
    for path in tmp.iterdir():
        if path.name != "mlflow.db":
            subprocess.run(["rm", "-rf", str(path)], check=True)
    start = time.perf_counter()
    done = subprocess.run(cmd, cwd=workdir, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd[:4])} failed:\n{done.stderr[-3000:]}")
    return wall


def stepping_loop_s(tmp: Path) -> float:
    attrs = json.loads((tmp / "out.zarr" / "zarr.json").read_text())["attributes"]
    return float(attrs["wall_time_s"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, required=True)
    ap.add_argument("--configfile", default="config/quick.yaml")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument(
        "--modes",
        nargs="+",
        choices=("spool", "live"),
        default=["spool", "live"],
        help="live alone for a checkout from before the spool (PYTHONPATH=OLD/src)",
    )
    ap.add_argument("--rules", nargs="+", choices=RULES, default=list(RULES))
    ap.add_argument("--against", type=Path, help="an older checkout, run alternately")
    args = ap.parse_args()
    base = {k: v for k, v in os.environ.items() if not k.startswith(("DOZERLAB_", "MLFLOW_"))}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d) / "out"
        tmp.mkdir()
        every = {
            "spool": {"DOZERLAB_PARENT_RUN_ID": "0" * 32, "DOZERLAB_MLFLOW_SPOOL": f"{d}/spool"},
            "live": {"MLFLOW_TRACKING_URI": f"sqlite:///{d}/mlflow.db"},
        }
        modes = {m: every[m] for m in args.modes}
        if args.against is not None:
            old = {"PYTHONPATH": str(args.against.resolve() / "src")}
            modes |= {f"{m} {args.against.name}": every[m] | old for m in args.modes}
        for rule in args.rules:
            cmd, env = retarget(command(args.workdir, args.configfile, rule), tmp)
            walls: dict[str, list[float]] = {m: [] for m in modes}
            loops: dict[str, list[float]] = {m: [] for m in modes}
            for _ in range(args.repeat):
                for mode, extra in modes.items():
                    walls[mode].append(run_once(cmd, {**base, **env, **extra}, args.workdir, tmp))
                    if rule == "simulate":
                        loops[mode].append(stepping_loop_s(tmp))
            for mode in modes:
                line = f"{rule:18s} {mode:14s} wall {statistics.median(walls[mode]):5.2f} s"
                line += f" (of {', '.join(f'{w:.2f}' for w in walls[mode])})"
                if loops[mode]:
                    over = [w - s for w, s in zip(walls[mode], loops[mode], strict=True)]
                    line += (
                        f", stepping loop {statistics.median(loops[mode]):.2f} s,"
                        f" overhead {statistics.median(over):.2f} s"
                    )
                print(line, flush=True)


if __name__ == "__main__":
    main()
