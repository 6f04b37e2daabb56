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
        "python -m dozerlab train-dynamics --model ridge --config config/quick.yaml \\\n"
        "      --train results/fields/hill/speed~1.0_depth~0.04.zarr \\\n"
        "              results/fields/hill/speed~1.5_depth~0.04.zarr \\\n"
        "      --out results/dynamics/ridge",
        models=MODELS,
        run="dozerlab.learn.dynamics.jobs:train_dynamics_job",
        results="dynamics",
        threads_key="dynamics",
        report=("dynamics ", "validation rollout loss", "windows"),
    )
    add_validation(
        sub,
        "validate-dynamics",
        "measure an evolution model's one-step and rollout errors on held-out points",
        "python -m dozerlab validate-dynamics --model results/dynamics/ridge \\\n"
        "      --config config/quick.yaml \\\n"
        "      --interpolation results/fields/hill/speed~1.25_depth~0.06.zarr \\\n"
        "      --extrapolation results/fields/hill/speed~0.75_depth~0.08.zarr \\\n"
        "      --out results/dynamics/ridge.json",
        run="dozerlab.learn.dynamics.jobs:validate_dynamics_job",
        models="dynamics",
        results="dynamics",
        plots="plots/NAME beside the JSON",
        sections="dynamics, mlflow sections",
    )
