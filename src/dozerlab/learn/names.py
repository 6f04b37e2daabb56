"""The force models' names, the one list of them: ``dozerlab train --model`` offers these, the
schema's ``learn.models`` enum must equal it (a test checks), and
:data:`dozerlab.learn.models.BACKBONES` has one backbone for each. A module of its own, without
torch, so that the CLI can offer the names without importing the models."""

from __future__ import annotations

#: Force/torque model names, in the report's order (docs/models.md).
MODEL_NAMES: tuple[str, ...] = ("linear", "mlp", "cnn", "unet")
