"""``dozerlab train-dynamics`` and ``validate-dynamics``: the field-evolution commands."""

from __future__ import annotations

import argparse

from dozerlab.learn.cli import add_training, add_validation

MODELS = ["persistence", "ridge", "unet"]


def register(sub: argparse._SubParsersAction) -> None:
    add_training(
        sub,
        "train-dynamics",
        "train one field-evolution model on field stores",
        models=MODELS,
        run="dozerlab.learn.dynamics.jobs:train_dynamics_job",
        results="dynamics",
        threads_key="dynamics",
        report=("dynamics ", "validation rollout loss", "windows"),
    )
    add_validation(
        sub,
        "validate-dynamics",
        "one-step and rollout errors of an evolution model on held-out points",
        run="dozerlab.learn.dynamics.jobs:validate_dynamics_job",
        models="dynamics",
        results="dynamics",
        plots="plots/NAME beside the JSON",
        sections="dynamics, mlflow sections",
    )
