"""The MLflow store under jobs that start together (what `snakemake --cores N` or a user's
shell loop does on a fresh project)."""

import os
import subprocess
import sys
import time

from mlflow.tracking import MlflowClient

JOB = """
import sys, time
start = float(sys.argv[1])
while time.time() < start:
    pass
from dozerlab.tracking import tracked_run
with tracked_run("job" + sys.argv[2], rule="test"):
    pass
"""


def test_jobs_started_together_on_a_fresh_store_all_record(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MLFLOW_", "DOZERLAB_"))}
    start = time.time() + 5.0  # past every interpreter's start-up, so they reach the store at once
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", JOB, str(start), str(i)],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in range(4)
    ]
    outputs = [p.communicate(timeout=120)[0] for p in procs]
    assert [p.returncode for p in procs] == [0] * 4, "\n".join(outputs)
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
    runs = client.search_runs([client.get_experiment_by_name("dozerlab").experiment_id])
    assert sorted(r.info.run_name for r in runs) == [f"job{i}" for i in range(4)]
