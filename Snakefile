# dozerlab: the whole sweep, from settled beds to the report. See README.md.
from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/scenarios.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/learn.smk"
include: "workflow/rules/dynamics.smk"
include: "workflow/rules/reduced.smk"
include: "workflow/rules/adaptive.smk"
include: "workflow/rules/report.smk"


localrules:
    all,


rule all:
    input:
        all_targets(),


# One parent MLflow run per invocation that runs jobs (Snakemake calls onstart only then, so a
# rerun with nothing to do logs nothing); every job's run is its child. On SLURM, jobs no node
# can hold are refused first, before anything is submitted or logged. From here on SIGTERM
# stops the jobs as Ctrl-C does (Snakemake's own handler would let them finish).
onstart:
    runtime.sigterm_as_ctrl_c()
    check_cluster_fit()
    start_parent_run()


onsuccess:
    print_summary()
    end_parent_run("FINISHED", log)


onerror:
    end_parent_run("FAILED", log)
