"""Field sampling (SPEC §5), the zarr field store, the thesis's binary format, the simulation run,
field plots and VTK snapshots.

Submodules: ``store`` (the zarr field store), ``sampling`` (the blade-attached bin grid and
particle–bin weights), ``legacy`` (the thesis's binary format), ``run`` (``dozerlab simulate``),
``plots`` (field slices, force series, animations), ``cli`` (the commands).
"""

from dozerlab.fields.store import FieldStoreWriter, open_store, write_store

__all__ = ["FieldStoreWriter", "open_store", "write_store"]
