"""The live reduced simulation (docs/models.md): the learned models drive the grains; measured against NDEM."""

#: The fields of the config's ``reduced`` section that a reduced run reads
#: (``simulation.ReducedSettings.from_config``): the workflow passes its reduce jobs only these,
#: so that changing the targets or the comparison's ``moved_radii`` reruns the comparison and
#: the report, not the runs. Here, not in ``simulation``, so that the Snakefile need not import
#: numba to read it.
LOOP_FIELDS = (
    "projection",
    "advect_margin",
    "crest_bins",
    "crest_models",
    "rest_speed",
    "support_angle",
    "divergence_overlap",
    "predicted_history",
    "step_rows",
    "density_models",
    "density_gain",
)
