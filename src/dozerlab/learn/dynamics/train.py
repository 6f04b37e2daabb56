"""Training of the evolution models: normalisation from the training windows, the ridge in
closed form, the U-Net by Adam through a few of its own calls (unrolled, with input noise) with
early stopping on that rollout loss over the validation blocks.

The losses weight the velocity error of each bin by its true density (empty bins' velocity is
a convention, not an observation), as the velocity metric does (:mod:`.metrics`).
"""

from __future__ import annotations

import math
import time
from typing import Any, Unpack

import numpy as np
import torch
from tqdm import tqdm

from dozerlab.learn.data import StoreData, split_train_validation
from dozerlab.learn.dynamics.models import FIELD_CHANNELS, DynamicsModel, RidgeStencil
from dozerlab.learn.dynamics.windows import WindowBatches, frame_of, windows
from dozerlab.learn.fitting import (
    EarlyStopping,
    EpochCallback,
    FitOptions,
    NormalEquations,
    adam,
    fit_start,
    guard,
)
from dozerlab.learn.train import TrainResult
from dozerlab.runtime import DozerlabError


def _chunks(n: int, size: int) -> list[np.ndarray]:
    return [np.arange(i, min(i + size, n)) for i in range(0, n, size)]


@torch.no_grad()
def fit_normalization(model: DynamicsModel, data: WindowBatches, limit: int = 512) -> float:
    """Set the model's channel, control and residual statistics and the range of the true
    fields from (at most ``limit``, evenly spread) training windows; returns the mean density of their bins (kg/m³), the scale of the
    loss's mass weights."""
    pick = np.unique(np.linspace(0, len(data) - 1, min(limit, len(data))).astype(int))
    xs, cs, res, rho_sum, count = [], [], [], 0.0, 0
    v_lo = torch.full((3,), math.inf)
    v_hi, rho_hi = -v_lo, torch.zeros(1)
    for sel in np.array_split(pick, max(1, len(pick) // 64)):
        v, rho, vb, v_true, rho_true = data.get(sel, model.horizon)
        base = model.base(v, rho, vb)
        x = torch.cat(
            [
                model.channels(v, rho, vb[:, : model.history]),
                model.channels(*base, vb[:, model.history :]),
            ],
            dim=1,
        )
        xs.append(x.transpose(0, 1).flatten(1).double())
        cs.append(vb.flatten(1).double())
        w = rho_true.double().unsqueeze(-1)
        dv = (v_true - base[0]).double()
        res.append(
            torch.cat(
                [
                    ((rho_true - base[1]).double() ** 2).sum().view(1),
                    (w * dv * dv).flatten(0, -2).sum(0),
                    w.sum().view(1),
                    torch.tensor([float(rho_true[..., 0].numel())], dtype=torch.float64),
                ]
            )
        )
        for a, b in ((v, rho), (v_true, rho_true)):
            v_lo = torch.minimum(v_lo, a.flatten(0, -2).min(0).values.cpu())
            v_hi = torch.maximum(v_hi, a.flatten(0, -2).max(0).values.cpu())
            rho_hi = torch.maximum(rho_hi, b.max().cpu().view(1))
        rho_sum += float(rho_true.double().sum())
        count += rho_true.numel()
    x, c, r = torch.cat(xs, 1), torch.cat(cs), torch.stack(res).sum(0)

    def std(a: torch.Tensor, dim: int) -> torch.Tensor:
        s = a.std(dim)
        return torch.where(s > 1e-6 * (s.max() + 1e-30), s, torch.ones_like(s))

    model.chan_mean.copy_(x.mean(1))
    model.chan_std.copy_(std(x, 1))
    model.cond_mean.copy_(c.mean(0))
    model.cond_std.copy_(std(c, 0))
    spread = torch.cat([(r[0] / r[5]).sqrt().view(1), (r[1:4] / r[4].clamp_min(1e-30)).sqrt()])
    model.res_std.copy_(torch.where(spread > 0, spread, torch.ones_like(spread)))
    # a tenth of the span as headroom: held-out runs may reach a little beyond the training ones
    margin = 0.1 * (v_hi - v_lo)
    bounds = (
        (model.v_lo, v_lo - margin),
        (model.v_hi, v_hi + margin),
        (model.rho_hi, 1.1 * rho_hi),
    )
    for buffer, value in bounds:
        buffer.copy_(value)
    return rho_sum / max(count, 1) or 1.0


def field_loss(
    model: DynamicsModel,
    pred: tuple[torch.Tensor, torch.Tensor],
    true_v: torch.Tensor,
    true_rho: torch.Tensor,
    rho_scale: float,
) -> torch.Tensor:
    """Mean squared error in units of the residual spread: density per bin, velocity per bin
    weighted by its true density over ``rho_scale``."""
    s = model.res_std
    e_rho = ((pred[1] - true_rho) / s[0]) ** 2
    e_v = (((pred[0] - true_v) / s[1:]) ** 2).sum(-1) * (true_rho / rho_scale)
    return e_rho.mean() + e_v.mean() / 3


@torch.no_grad()
def fit_ridge(
    model: DynamicsModel,
    data: WindowBatches,
    val: WindowBatches,
    alphas: list[float],
    every: int,
    rho_scale: float,
    calls: int,
    on_alpha: EpochCallback | None = None,
    progress: bool = True,
) -> tuple[list[float], list[float], int]:
    """Closed-form ridge of the normalised residuals on every ``every``-th training window, one
    fit per layer of bins along x and box of its bands: density unweighted, velocity weighted
    by true density, one solve per predicted row. Each of ``alphas`` is solved from the same normal equations and
    the one whose ``calls``-call rollouts on ``val`` have the lowest loss is kept: a linear map
    fed its own output can amplify, which one row ahead does not show. Returns the one-step
    training and the rollout validation loss of each alpha, and the index of the kept one.
    ``progress``: a tqdm bar over the batches of windows on stderr."""
    net, m, layers = model.net, model.horizon, model.grid[0]
    assert isinstance(net, RidgeStencil)
    d = net.weight.shape[2]
    parts = [(i, k, rows) for i in range(layers) for k, rows in enumerate(net.box_rows(model.grid))]
    eq_rho = [NormalEquations(d, m) for _ in parts]
    eq_v = [[NormalEquations(d, 3) for _ in range(m)] for _ in parts]
    pick = np.arange(0, len(data), max(1, every))
    batches = np.array_split(pick, max(1, len(pick) // 16))
    for sel in tqdm(batches, desc="ridge", unit="batch", disable=not progress):
        v, rho, vb, v_true, rho_true = data.get(sel, m)
        base = model.base(v, rho, vb)
        x, c = model.inputs(v, rho, vb, base)
        rows = net.design(x, model.coords, c)  # B, X, YZ, d
        y_rho = ((rho_true - base[1]) / model.res_std[0]).flatten(3)  # B, m, X, YZ
        y_v = ((v_true - base[0]) / model.res_std[1:]).flatten(3, 4)  # B, m, X, YZ, 3
        w_v = (rho_true / rho_scale).flatten(3)
        for p, (i, _, idx) in enumerate(parts):
            r = rows[:, i, idx].reshape(-1, d).double()  # once for the part's four sums
            eq_rho[p].add(r, y_rho[:, :, i, idx].permute(0, 2, 1).reshape(-1, m))
            for j in range(m):
                eq_v[p][j].add(r, y_v[:, j, i, idx].reshape(-1, 3), w_v[:, j, i, idx].reshape(-1))
    train_loss, val_loss, states = [], [], []
    for a, alpha in enumerate(alphas):
        for p, (i, k, _) in enumerate(parts):
            w_rho, b_rho = eq_rho[p].solve(alpha)
            for j in range(m):
                w_vel, b_vel = eq_v[p][j].solve(alpha)
                f = FIELD_CHANNELS * j
                net.weight[i, k, :, f] = w_rho[:, j].float()
                net.bias[i, k, f] = float(b_rho[j])
                net.weight[i, k, :, f + 1 : f + FIELD_CHANNELS] = w_vel.float()
                net.bias[i, k, f + 1 : f + FIELD_CHANNELS] = b_vel.float()
        train_loss.append(_mean_loss(model, data, 1, rho_scale))
        val_loss.append(_mean_loss(model, val, calls, rho_scale))
        states.append({n: p.clone() for n, p in net.state_dict().items()})
        if on_alpha:
            on_alpha(a, train_loss[-1], val_loss[-1])
    finite = [v if math.isfinite(v) else math.inf for v in val_loss]
    best = int(np.argmin(finite))
    guard(
        finite[best],
        "the validation rollout loss of every ridge alpha",
        "raise dynamics.ridge_alphas",
    )
    net.load_state_dict(states[best])
    return train_loss, val_loss, best


def unrolled_loss(
    model: DynamicsModel,
    batch: tuple[torch.Tensor, ...],
    calls: int,
    rho_scale: float,
    noise: float = 0.0,
    gen: torch.Generator | None = None,
) -> torch.Tensor:
    """Mean loss over ``calls`` successive calls, each fed the model's own previous output.

    ``batch`` as :meth:`WindowBatches.get` returns it with horizon calls·m. ``noise`` adds
    Gaussian noise of that many channel spreads to the first input rows (density kept >= 0)."""
    v, rho, vb, v_true, rho_true = batch
    h, m = model.history, model.horizon
    if noise > 0:
        sv = model.chan_std[1:4].view(1, 1, 1, 1, 1, 3)
        v = v + noise * sv * torch.randn(v.shape, generator=gen, device=v.device)
        noise_rho = torch.randn(rho.shape, generator=gen, device=rho.device)
        rho = (rho + noise * model.chan_std[0] * noise_rho * (rho > 0)).clamp_min(0)
    total = torch.zeros((), device=v.device)
    for k in range(calls):
        pred = model(v, rho, vb[:, k * m : k * m + h + m])
        total = total + field_loss(
            model, pred, v_true[:, k * m : (k + 1) * m], rho_true[:, k * m : (k + 1) * m], rho_scale
        )
        v = torch.cat([v, pred[0]], 1)[:, -h:]
        rho = torch.cat([rho, pred[1]], 1)[:, -h:]
    return total / calls


def train_dynamics(
    kind: str, stores: list[StoreData], config: dict[str, Any], **options: Unpack[FitOptions]
) -> TrainResult:
    """Train evolution model ``kind`` on ``stores`` (the training points) with
    ``config['dynamics']``; early stopping on the blocks of ``learn.validation_fraction`` /
    ``learn.validation_block`` (those of the force models). ``options`` as
    :class:`~dozerlab.learn.fitting.FitOptions`."""
    dyn, learn = config["dynamics"], config["learn"]
    seed, dev, on_epoch, progress = fit_start(config, options)
    row_dt, bin_size = frame_of(stores)
    ridge = kind == "ridge"
    h, m = dyn["history"], dyn["ridge_horizon" if ridge else "horizon"]
    calls, val_calls = (dyn["unroll"] if kind == "unet" else 1), dyn["val_rollout"]
    fraction, block = learn["validation_fraction"], learn["validation_block"]
    # the same blocks either way: windows differ only at each store's end
    train_s, _ = split_train_validation(windows(stores, h, m * calls), fraction, block)
    _, val_s = split_train_validation(windows(stores, h, m * val_calls), fraction, block)
    train, val = WindowBatches(train_s, dev), WindowBatches(val_s, dev)
    grid = stores[0].grid
    # the ridge's own split of each layer into boxes; the other models have none
    bands = {a: tuple(dyn[f"ridge_{a}_bands"]) if ridge else () for a in ("y", "z")}
    for axis, n in (("y", grid[1]), ("z", grid[2])):
        if any(not 0 < e < n for e in bands[axis]):
            raise DozerlabError(
                f"config field 'dynamics.ridge_{axis}_bands': {list(bands[axis])} does not fit the "
                f"training stores' {n} bins along {axis} (allowed: edges within 1..{n - 1})"
            )
    model = DynamicsModel(
        kind,
        grid,
        h,
        m,
        row_dt,
        bin_size,
        dyn["width"],
        bands["y"],
        bands["z"],
        momentum=ridge and dyn["ridge_momentum"],
    ).to(dev)
    result = TrainResult(model, samples={"train": len(train), "validation": len(val)})
    t0 = time.perf_counter()
    rho_scale = fit_normalization(model, train)
    if kind == "ridge":
        result.train_loss, result.val_loss, result.best_epoch = fit_ridge(
            model,
            train,
            val,
            dyn["ridge_alphas"],
            dyn["ridge_every"],
            rho_scale,
            val_calls,
            on_epoch,
            progress,
        )
        result.penalty = float(dyn["ridge_alphas"][result.best_epoch])
    elif kind == "unet":
        _fit_unet(model, train, val, dyn, seed, rho_scale, result, on_epoch, progress)
    else:
        tr, va = (
            _mean_loss(model, train, 1, rho_scale),
            _mean_loss(model, val, val_calls, rho_scale),
        )
        result.train_loss, result.val_loss = [tr], [va]
        if on_epoch:
            on_epoch(0, tr, va)
    result.seconds = time.perf_counter() - t0
    model.eval()
    return result


@torch.no_grad()
def _mean_loss(
    model: DynamicsModel, data: WindowBatches, calls: int, rho_scale: float, limit: int = 128
) -> float:
    model.eval()
    pick = np.unique(np.linspace(0, len(data) - 1, min(limit, len(data))).astype(int))
    total = 0.0
    for sel in np.array_split(pick, max(1, len(pick) // 32)):
        batch = data.get(sel, model.horizon * calls)
        total += float(unrolled_loss(model, batch, calls, rho_scale)) * len(sel)
    return total / len(pick)


def _fit_unet(
    model: DynamicsModel,
    train: WindowBatches,
    val: WindowBatches,
    dyn: dict[str, Any],
    seed: int,
    rho_scale: float,
    result: TrainResult,
    on_epoch: EpochCallback | None,
    progress: bool,
) -> None:
    calls = dyn["unroll"]
    opt = adam(model.parameters(), dyn["learning_rate"])
    gen = np.random.default_rng(seed)
    tgen = torch.Generator(device=train.device).manual_seed(seed)
    stop = EarlyStopping(model, dyn["patience"], on_epoch)
    bar = tqdm(
        range(dyn["epochs"]), desc="train unet (dynamics)", unit="epoch", disable=not progress
    )
    for epoch in bar:
        model.train()
        order = gen.permutation(len(train))[: dyn["samples_per_epoch"]]
        total = 0.0
        for sel in _chunks(len(order), dyn["batch_size"]):
            batch = train.get(order[sel], model.horizon * calls)
            loss = unrolled_loss(model, batch, calls, rho_scale, dyn["noise"], tgen)
            value = float(loss.detach())
            guard(value, f"the training loss at epoch {epoch}", "lower dynamics.learning_rate")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += value * len(sel)
        tr = total / len(order)
        va = _mean_loss(model, val, dyn["val_rollout"], rho_scale)
        guard(va, f"the validation rollout loss at epoch {epoch}", "lower dynamics.learning_rate")
        bar.set_postfix(train=f"{tr:.4f}", val=f"{va:.4f}")
        if stop.end_epoch(epoch, tr, va):
            break
    result.train_loss, result.val_loss, result.best_epoch = stop.restore()
