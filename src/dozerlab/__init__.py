"""dozerlab: data-driven model reduction of granular bulldozing.

Layers, lowest first (a layer imports only those before it): ``ndem`` (the non-smooth DEM
engine) → ``scenarios`` (beds, trajectories) → ``fields`` (sampling, stores) → ``learn``
(datasets, models, validation) → ``report``. ``config``, ``runtime`` and ``tracking`` are
shared utilities any layer may use; ``cli`` sits on top.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dozerlab")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+unknown"
