"""Pieces every trainer shares: the device, the samples as tensors, the divergence guard and the
closed-form ridge solvers (one on a design matrix held whole, one on normal equations
accumulated in chunks)."""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Iterable
from typing import Any, TypedDict

import torch

from dozerlab.learn.data import Samples
from dozerlab.runtime import DozerlabError


class TrainingDiverged(DozerlabError):
    """The loss became NaN or infinite."""


def device_for(name: str | None = None) -> torch.device:
    """``name`` if given, else CUDA when present, else CPU. A name that is no torch device, or
    a device this machine lacks (``cuda`` without CUDA, ``cuda:3`` with two GPUs, ``mps`` off
    Apple), is refused with :class:`DozerlabError` naming it (``--device``)."""
    if not name:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise DozerlabError(
            f"--device '{name}' is not a torch device (allowed: cpu, cuda, cuda:N, mps)"
        ) from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise DozerlabError(
                f"--device '{name}': CUDA is not available here (torch {torch.__version__}, "
                f"{'built without CUDA' if torch.version.cuda is None else 'no GPU visible'}); "
                "use --device cpu or leave --device out"
            )
        if device.index is not None and device.index >= count:
            raise DozerlabError(
                f"--device '{name}': this machine has {count} CUDA device(s) "
                f"(allowed: cuda:0 to cuda:{count - 1})"
            )
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise DozerlabError(
            f"--device '{name}': Apple's MPS is not available here; use --device cpu"
        )
    elif device.type not in ("cpu", "mps"):
        raise DozerlabError(f"--device '{name}' is not supported (allowed: cpu, cuda, cuda:N, mps)")
    return device


#: ``on_epoch(epoch, train_loss, val_loss)``, called after each epoch.
EpochCallback = Callable[[int, float, float], None]


class FitOptions(TypedDict, total=False):
    """How a training runs, the keywords every trainer takes: ``device`` (a torch device name;
    default CUDA when present, else CPU), ``on_epoch`` (an :data:`EpochCallback`; default none)
    and ``progress`` (a tqdm bar on stderr; default True)."""

    device: str | None
    on_epoch: EpochCallback | None
    progress: bool


def fit_start(
    config: dict[str, Any], options: FitOptions
) -> tuple[int, torch.device, EpochCallback | None, bool]:
    """A trainer's start: torch seeded with the config's ``seed``; returns the seed, the
    device, the epoch callback and the progress flag of ``options`` (defaults filled in)."""
    seed = int(config.get("seed", 0))
    torch.manual_seed(seed)
    device = device_for(options.get("device"))
    return seed, device, options.get("on_epoch"), options.get("progress", True)


def adam(
    params: Iterable[torch.nn.Parameter], lr: float, weight_decay: float = 0.0
) -> torch.optim.Adam:
    """Adam with torch's fused kernel: one pass over each parameter per step where the default
    makes a dozen (the MLP's 4.7 M parameters, CPU, 1 thread: 90 -> 16 ms per step; the
    updates agree to round-off, BENCHMARKS.md)."""
    return torch.optim.Adam(params, lr=lr, weight_decay=weight_decay, fused=True)


class SampleTensors:
    """The per-row store arrays of ``samples`` (velocity, density, blade_velocity) as tensors on
    ``device``; a trainer's batches gather rows of them by index."""

    def __init__(self, samples: Samples, device: torch.device) -> None:
        self.samples, self.device = samples, device
        self.velocity = torch.from_numpy(samples.velocity).to(device)
        self.density = torch.from_numpy(samples.density).to(device)
        self.blade_velocity = torch.from_numpy(samples.blade_velocity).to(device)

    def __len__(self) -> int:
        return len(self.samples)


def guard(value: float, what: str, hint: str = "lower the learning rate") -> None:
    """Raise :class:`TrainingDiverged` naming ``what`` when ``value`` is NaN or infinite."""
    if not math.isfinite(value):
        raise TrainingDiverged(
            f"training diverged: {what} is {value}; check the stores for non-finite values or {hint}"
        )


def solve_ridge(
    x: torch.Tensor, y: torch.Tensor, alpha: float, *, center: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """Ridge regression y ≈ x w + b minimising mean squared error + ``alpha``·‖w‖² over
    standardised columns of x (intercept unpenalised; none when ``center`` is False).

    x (N, D), y (N, K), float64; returns w (D, K) and b (K,) in the units of x and y. Solved in
    the dual (N×N) when features outnumber samples; it cannot diverge.
    """
    if alpha < 0:
        raise ValueError(f"ridge alpha must be >= 0, got {alpha}")
    n, d = x.shape
    xm, ym = (x.mean(0), y.mean(0)) if center else (torch.zeros_like(x[0]), torch.zeros_like(y[0]))
    xs = x.std(0).clamp_min(1e-12)
    x = (x - xm) / xs
    lam = alpha * n + 1e-9 * n
    if d > n:
        gram = x @ x.T
        gram.diagonal().add_(lam)
        w = x.T @ torch.linalg.solve(gram, y - ym)
    else:
        a = x.T @ x
        a.diagonal().add_(lam)
        w = torch.linalg.solve(a, x.T @ (y - ym))
    w = w / xs[:, None]
    return w, ym - xm @ w


def gram(a: torch.Tensor) -> torch.Tensor:
    """aᵀa (D, D) for ``a`` (N, D), in ``a``'s precision. On the CPU through numpy, whose
    ``a.T @ a`` of one buffer is BLAS's symmetric rank-k update: half the multiplications of a
    product."""
    if a.device.type != "cpu":
        return a.T @ a
    rows = a.detach().contiguous().numpy()
    return torch.from_numpy(rows.T @ rows)


class NormalEquations:
    """Weighted ridge regression from design rows added in chunks (too many to hold at once).

    ``add(x (N, D), y (N, K), weight (N,) >= 0 or None)`` accumulates the weighted moments in
    float64; ``solve(alpha)`` minimises the weighted mean squared error + ``alpha``·‖w‖² over
    standardised columns, intercept unpenalised, and returns w (D, K) and b (K,).
    """

    def __init__(self, d: int, k: int) -> None:
        f64 = torch.float64
        self.sw = torch.zeros((), dtype=f64)
        self.sx, self.sy = torch.zeros(d, dtype=f64), torch.zeros(k, dtype=f64)
        self.sxx, self.sxy = torch.zeros(d, d, dtype=f64), torch.zeros(d, k, dtype=f64)

    def add(self, x: torch.Tensor, y: torch.Tensor, weight: torch.Tensor | None = None) -> None:
        if weight is not None:
            if bool((weight < 0).any()):
                raise ValueError("ridge row weights must be >= 0")
            # a row of weight 0 adds nothing to any sum: the ridge's velocity rows are weighted
            # by density, and 41 % of the default sweep's bins are empty (BENCHMARKS.md)
            keep = weight != 0
            if not bool(keep.all()):
                x, y, weight = x[keep], y[keep], weight[keep]
        d = x.shape[1]
        # the sums are made on the rows' device and kept on the CPU
        self.sw += x.shape[0] if weight is None else weight.double().sum().cpu()
        self.sx += (x if weight is None else x * weight[:, None]).double().sum(0).cpu()
        self.sy += (y if weight is None else y * weight[:, None]).double().sum(0).cpu()
        # xᵀWx and xᵀWy from one Gram of the rows and targets scaled by √w, in float64: the
        # ridge's rollouts amplify its weights' rounding, and float32 products made its
        # validation rollout loss a draw of the summation order (2.88-6.8 on the default
        # sweep, 2.861 in float64 whatever the order; BENCHMARKS.md, "The ridge's normal
        # equations in float64")
        xy = torch.cat([x, y.to(x.dtype)], 1).double()
        g = gram(xy if weight is None else xy * weight.double().sqrt()[:, None]).cpu()
        self.sxx += g[:d, :d]
        self.sxy += g[:d, d:]

    def solve(self, alpha: float) -> tuple[torch.Tensor, torch.Tensor]:
        if alpha < 0:
            raise ValueError(f"ridge alpha must be >= 0, got {alpha}")
        if float(self.sw) <= 0:
            raise DozerlabError("ridge regression without samples (all weights zero)")
        n = self.sw
        xm, ym = self.sx / n, self.sy / n
        cov = self.sxx / n - torch.outer(xm, xm)
        cxy = self.sxy / n - torch.outer(xm, ym)
        var = cov.diagonal().clamp_min(0)
        # a column constant over the rows carries nothing; rounding leaves it a variance of
        # about 1e-16 of its mean square, which standardising would blow up to unit noise
        live = ((var > 1e-10 * var.max()) & (var > 1e-12 * self.sxx.diagonal() / n)).double()
        xs = torch.where(live > 0, var.sqrt(), torch.ones_like(var))
        a = cov * torch.outer(live, live) / torch.outer(xs, xs)
        a.diagonal().add_(alpha + 1e-9)
        w = torch.linalg.solve(a, cxy * live[:, None] / xs[:, None]) / xs[:, None]
        guard(float(w.abs().max()), "the ridge solution", "raise the ridge alpha")
        return w, ym - xm @ w


class EarlyStopping:
    """The epochs' losses, the model's best state by validation loss, and when to stop:
    ``end_epoch`` records an epoch (and passes it to ``on_epoch``) and says whether ``patience``
    epochs in a row brought no better validation loss; ``restore`` loads the best state and
    returns the history."""

    def __init__(
        self,
        model: torch.nn.Module,
        patience: int,
        on_epoch: Callable[[int, float, float], None] | None = None,
    ) -> None:
        self.model, self.patience, self.on_epoch = model, patience, on_epoch
        self.train_loss: list[float] = []
        self.val_loss: list[float] = []
        self.best, self.best_epoch, self.waited = math.inf, 0, 0
        self.state = copy.deepcopy(model.state_dict())

    def end_epoch(self, epoch: int, train_loss: float, val_loss: float) -> bool:
        self.train_loss.append(train_loss)
        self.val_loss.append(val_loss)
        if self.on_epoch:
            self.on_epoch(epoch, train_loss, val_loss)
        if val_loss < self.best:
            self.best, self.best_epoch, self.waited = val_loss, epoch, 0
            self.state = copy.deepcopy(self.model.state_dict())
            return False
        self.waited += 1
        return self.waited >= self.patience

    def restore(self) -> tuple[list[float], list[float], int]:
        """Load the best state; returns the training and validation losses per epoch and the
        best epoch (a training result's history)."""
        self.model.load_state_dict(self.state)
        return self.train_loss, self.val_loss, self.best_epoch
