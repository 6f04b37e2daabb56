"""Field sampling (docs/data.md), the zarr field store, the thesis's binary format, the simulation run,
field plots and VTK snapshots.

Submodules: ``store`` (the zarr field store), ``reader`` (its fast reader), ``sampling`` (the
blade-attached bin grid and particle–bin weights), ``legacy`` (the thesis's binary format),
``run`` (the stepping loop), ``jobs`` (the ``dozerlab simulate`` job), ``plots`` (field slices,
force series, animations), ``cli`` (the commands). Kept import-light: the CLI imports this
package to list its commands, so import what you use from its submodule.
"""
