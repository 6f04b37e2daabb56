# dozerlab: the whole sweep, from settled beds to the report. See README.md.
from snakemake.utils import min_version

min_version("9.0")

configfile: "config/config.yaml"


include: "workflow/rules/common.smk"


rule all:
    input:
        all_targets(),
