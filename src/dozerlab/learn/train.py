"""Training: normalisation from the training block, Adam with a plateau schedule and early
stopping on the validation block, or the closed-form ridge solution for ``linear``."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Unpack

import numpy as np
import torch
from tqdm import tqdm

from dozerlab.learn.data import Samples, StoreData, concat, split_train_validation
from dozerlab.learn.fitting import (
    EarlyStopping,
    EpochCallback,
    FitOptions,
    SampleTensors,
    TrainingDiverged,
    adam,
    device_for,
    fit_start,
    guard,
    solve_ridge,
)
from dozerlab.learn.models import TARGET_PARITY, ForceModel, LinearHead, channel_parity

__all__ = ["TrainResult", "TrainingDiverged", "device_for", "train_model"]


@dataclass
class TrainResult:
    """A trained model with its loss history (per epoch) and timing (s). A closed-form fit
    over candidate penalties has one "epoch" per penalty and ``penalty``, the one it kept."""

    model: Any  # a ForceModel, or a DynamicsModel from learn.dynamics.train
    train_loss: list[float] = field(default_factory=list)
    val_loss: list[float] = field(default_factory=list)
    best_epoch: int = 0
    samples: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    data_seconds: float = 0.0
    model_uri: str = ""
    penalty: float | None = None


class Batches(SampleTensors):
    """The samples and their targets as tensors on ``device``; ``get(sel)`` gathers one batch
    by index."""

    def __init__(self, samples: Samples, device: torch.device) -> None:
        super().__init__(samples, device)
        self.target = torch.from_numpy(samples.target).to(device)

    def get(self, sel: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(velocity, density, blade_velocity) with a history axis, and the (B, 6) targets."""
        rows = torch.from_numpy(self.samples.rows(sel)).to(self.device)
        cur = rows[:, -1]
        return self.velocity[rows], self.density[rows], self.blade_velocity[rows], self.target[cur]

    def chunks(
        self, size: int
    ) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
        for start in range(0, len(self), size):
            yield self.get(np.arange(start, min(start + size, len(self))))


def mirror_y(
    velocity: torch.Tensor,
    density: torch.Tensor,
    blade_velocity: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
) -> None:
    """Reflect the samples where ``mask`` holds across the blade's centre plane, in place.

    Beds and blade are symmetric in y, so the reflected sample is as valid as the
    original: bins are reversed along y, the y components of velocities and force change sign,
    and so do torque_x and torque_z (axial vector, torque about the tip). Shapes as
    :meth:`Batches.get` returns them.
    """
    flip = torch.tensor([1.0, -1.0, 1.0], device=velocity.device)
    velocity[mask] = velocity[mask].flip(3) * flip
    density[mask] = density[mask].flip(3)
    blade_velocity[mask] = blade_velocity[mask] * flip
    target[mask] = target[mask] * torch.tensor(TARGET_PARITY, device=target.device)


@torch.no_grad()
def fit_normalization(model: ForceModel, train: Batches, chunk: int = 256) -> None:
    """Set the model's channel, conditioning and target statistics from the training samples.

    Quantities that are odd under the mirror y → −y (lateral velocities, force_y, …) are
    centred at zero, as the symmetry of beds and blade says, and scaled by their RMS."""
    sums: dict[str, torch.Tensor] = {}
    n_bins = n_cond = 0
    for v, rho, vb, y in train.chunks(chunk):
        x, c = model.raw_features(v, rho, vb)
        x, c, y = x.double(), c.double(), y.double()
        for name, value in (
            ("x", x.sum(dim=(0, 2, 3, 4))),
            ("x2", (x * x).sum(dim=(0, 2, 3, 4))),
            ("c", c.sum(0)),
            ("c2", (c * c).sum(0)),
            ("y", y.sum(0)),
            ("y2", (y * y).sum(0)),
        ):
            sums[name] = sums[name] + value if name in sums else value
        n_bins += x.shape[0] * x[0, 0].numel()
        n_cond += x.shape[0]

    chan_par, cond_par = channel_parity(model.history, model.contact)
    odd = {
        key: torch.tensor(par, device=sums["y"].device) < 0
        for key, par in (("x", chan_par), ("c", cond_par), ("y", TARGET_PARITY))
    }

    def mean_std(name: str, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        mean = torch.where(odd[name], 0.0, sums[name] / n)
        sd = torch.sqrt(torch.clamp(sums[name + "2"] / n - mean * mean, min=0.0))
        # A channel constant over the training points (no lateral blade motion, say) is centred only.
        return mean, torch.where(sd > 1e-6 * (sd.max() + 1e-30), sd, torch.ones_like(sd))

    for key, buffers, n in (
        ("x", ("chan_mean", "chan_std"), n_bins),
        ("c", ("cond_mean", "cond_std"), n_cond),
        ("y", ("y_mean", "y_std"), n_cond),
    ):
        for buffer, value in zip(buffers, mean_std(key, n), strict=True):
            getattr(model, buffer).copy_(value)


@torch.no_grad()
def mean_loss(model: ForceModel, data: Batches, chunk: int = 256) -> float:
    """Mean squared error of the normalised targets over ``data``."""
    model.eval()
    total, n = 0.0, 0
    for v, rho, vb, y in data.chunks(chunk):
        err = model.normalized(v, rho, vb) - (y - model.y_mean) / model.y_std
        total += float((err * err).sum())
        n += err.numel()
    return total / max(n, 1)


def _guard(value: float, what: str) -> None:
    guard(value, what, "lower learn.learning_rate")


@torch.no_grad()
def fit_ridge(model: ForceModel, train: Batches, alpha: float, chunk: int = 256) -> None:
    """Closed-form ridge regression of the normalised targets, one solve per target parity:
    minimises mean squared error + ``alpha``·‖w‖² over standardised design columns (intercept
    unpenalised). Solved in the dual (N×N) when features outnumber samples; it cannot diverge."""
    if alpha < 0:
        raise ValueError(f"learn.ridge_alpha must be >= 0, got {alpha}")
    head = model.backbone
    if not isinstance(head, LinearHead):
        raise TypeError(f"fit_ridge fits a LinearHead backbone, got {type(head).__name__}")
    rows: list[list[torch.Tensor]] = [[], []]
    ys = []
    for v, rho, vb, y in train.chunks(chunk):
        for part, design in zip(rows, head.designs(*model.inputs(v, rho, vb)), strict=True):
            part.append(design.double())
        ys.append(((y - model.y_mean) / model.y_std).double())
    y_all = torch.cat(ys)
    for fc, part, odd in ((head.even, rows[0], False), (head.odd, rows[1], True)):
        # odd features and targets have zero mean by symmetry: no intercept, so that the odd
        # prediction changes sign exactly with the mirrored input
        w, b = solve_ridge(torch.cat(part), y_all[:, head.target_odd == odd], alpha, center=not odd)
        guard(float(w.abs().max()), "the ridge solution", "raise learn.ridge_alpha")
        fc.weight.copy_(w.T.float())
        fc.bias.copy_(b.float())


def train_model(
    kind: str, stores: list[StoreData], config: dict[str, Any], **options: Unpack[FitOptions]
) -> TrainResult:
    """Train model ``kind`` on ``stores`` (the training points) with ``config['learn']``.

    ``learn.validation_fraction`` of each store (blocks of ``learn.validation_block`` steps spread
    over the run, or its end when that is 0) is held out for early stopping; normalisation uses
    the rest. ``options`` as :class:`~dozerlab.learn.fitting.FitOptions`; ``on_epoch(epoch,
    train_loss, val_loss)`` is called after each epoch (losses: normalised MSE). Raises
    :class:`TrainingDiverged` on NaN/inf.
    """
    learn = config["learn"]
    seed, dev, on_epoch, progress = fit_start(config, options)
    samples = concat(stores, learn["history"])
    train_s, val_s = split_train_validation(
        samples, learn["validation_fraction"], learn["validation_block"]
    )
    train, val = Batches(train_s, dev), Batches(val_s, dev)
    model = ForceModel(
        kind, stores[0].grid, learn["history"], learn["contact"], stores[0].blade_part
    ).to(dev)
    fit_normalization(model, train)
    result = TrainResult(model, samples={"train": len(train), "validation": len(val)})
    t0 = time.perf_counter()
    if kind == "linear":
        fit_ridge(model, train, learn["ridge_alpha"])
        result.train_loss, result.val_loss = [mean_loss(model, train)], [mean_loss(model, val)]
        _guard(result.val_loss[0], "the validation loss")
        if on_epoch:
            on_epoch(0, result.train_loss[0], result.val_loss[0])
    else:
        _fit_gradient(model, train, val, learn, seed, result, on_epoch, progress)
    result.seconds = time.perf_counter() - t0
    model.eval()
    return result


def _fit_gradient(
    model: ForceModel,
    train: Batches,
    val: Batches,
    learn: dict[str, Any],
    seed: int,
    result: TrainResult,
    on_epoch: EpochCallback | None,
    progress: bool,
) -> None:
    opt = adam(model.parameters(), learn["learning_rate"], learn["weight_decay"])
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(
        opt, factor=0.5, patience=learn["lr_patience"]
    )
    gen = np.random.default_rng(seed)
    stop = EarlyStopping(model, learn["patience"], on_epoch)
    bar = tqdm(
        range(learn["epochs"]), desc=f"train {model.kind}", unit="epoch", disable=not progress
    )
    for epoch in bar:
        model.train()
        order, total, count = gen.permutation(len(train)), 0.0, 0
        for start in range(0, len(order), learn["batch_size"]):
            t_data = time.perf_counter()
            v, rho, vb, y = train.get(order[start : start + learn["batch_size"]])
            if learn["mirror"]:
                mirror_y(v, rho, vb, y, torch.from_numpy(gen.random(y.shape[0]) < 0.5).to(y.device))
            result.data_seconds += time.perf_counter() - t_data
            loss = torch.nn.functional.mse_loss(
                model.normalized(v, rho, vb), (y - model.y_mean) / model.y_std
            )
            value = float(loss.detach())
            _guard(value, f"the training loss at epoch {epoch}")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total, count = total + value * y.shape[0], count + y.shape[0]
        val_loss = mean_loss(model, val)
        _guard(val_loss, f"the validation loss at epoch {epoch}")
        sched.step(val_loss)
        bar.set_postfix(train=f"{total / count:.4f}", val=f"{val_loss:.4f}")
        if stop.end_epoch(epoch, total / count, val_loss):
            break
    result.train_loss, result.val_loss, result.best_epoch = stop.restore()
