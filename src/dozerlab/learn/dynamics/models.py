"""The evolution models: ``persistence``, ``ridge`` and ``unet``, each a :class:`DynamicsModel`.

Raw store arrays in, the fields of the next m rows out, in physical units. ``persistence``
repeats the last row (the baseline). The others start from the last row carried m rows ahead by
:func:`~dozerlab.learn.dynamics.advection.advect` (the frame shift and the material's own
motion made explicit) and add a learned correction, in units of the training residuals' spread:
``ridge`` a closed-form linear map of each bin's 3×3×3 neighbourhood of the channels, its
position and the blade control (a 3D convolution fitted by ridge regression, with weights per
layer along x and band of heights; it cannot diverge), ``unet`` a small 3D U-Net on the same channels. Input channels per history row: the
density and the velocity relative to that row's blade velocity; per predicted row: the advected
density and velocity relative to the blade; with ``momentum`` (the ridge's
``dynamics.ridge_momentum``) also the momentum density relative to the blade, ρ(v − v_blade),
which a linear map of the fields alone cannot form. Normalisation lives in buffers, so a state
dict is the whole model.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from dozerlab.learn.dynamics.advection import advect
from dozerlab.learn.models import Conv3d, pad_even, resize_trilinear

DYNAMICS_MODELS = ("persistence", "ridge", "unet")
#: Field channels of a row: density, then the three velocity components.
FIELD_CHANNELS = 4
#: Input channels of a row with momentum: the field channels, then ρ(v − v_blade) over
#: :data:`MOMENTUM_DENSITY` (velocity's units).
MOMENTUM_CHANNELS = 7
MOMENTUM_DENSITY = 1000.0


def coordinates(grid: tuple[int, int, int]) -> torch.Tensor:
    """(3, X, Y, Z) bin positions scaled to [-1, 1] along each axis."""
    axes = [torch.linspace(-1.0, 1.0, n) if n > 1 else torch.zeros(1) for n in grid]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"))


class RidgeStencil(nn.Module):
    """Linear in each bin's 3×3×3 neighbourhood of the channels (edges replicated), its
    position and the blade control, with weights of its own for each layer of bins along x
    (distance from the blade) and, in it, each box of the bands along y and z: the front
    layer, where unknown material enters, and the layers at the blade face follow other rules
    than the middle, the row straddling the cut others than the pile's top. Fitted in closed
    form (:mod:`.train`). ``weight`` (X, boxes, d, outputs), ``bias`` (X, boxes, outputs).
    """

    def __init__(
        self,
        channels: int,
        cond: int,
        outputs: int,
        grid: tuple[int, int, int],
        y_bands: tuple[int, ...] = (),
        z_bands: tuple[int, ...] = (),
    ) -> None:
        super().__init__()
        d = 27 * channels + 3 + cond
        self.boxes = band_boxes(grid, y_bands, z_bands)
        self.weight = nn.Parameter(torch.zeros(grid[0], len(self.boxes), d, outputs))
        self.bias = nn.Parameter(torch.zeros(grid[0], len(self.boxes), outputs))

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
        # models saved before the bands held one box: weight (X, d, outputs), bias (X, outputs)
        for name, dim in (("weight", 3), ("bias", 2)):
            t = state_dict.get(prefix + name)
            if t is not None and t.dim() == dim and len(self.boxes) == 1:
                state_dict[prefix + name] = t.unsqueeze(1)
        super()._load_from_state_dict(state_dict, prefix, *args)

    def box_rows(self, grid: tuple[int, int, int]) -> list[torch.Tensor]:
        """For each box, the indices y·Z + z of its bins in a (Y·Z) row of :meth:`design`."""
        nz = grid[2]
        return [
            (torch.arange(y0, y1)[:, None] * nz + torch.arange(z0, z1)[None, :]).flatten()
            for y0, y1, z0, z1 in self.boxes
        ]

    @staticmethod
    def stencil(x: torch.Tensor) -> torch.Tensor:
        """Each bin's 3×3×3 neighbourhood of ``x`` (B, C, X, Y, Z) as (B, X, Y·Z, 27, C),
        neighbour 9i + 3j + k (edges replicated): the design rows the closed-form fit reads.

        Stacked from 27 shifted views of the channel-last padded grid: contiguous writes, where
        reshaping the unfolded grid gathered element by element (0.4 ms against 1.5 ms on the
        16 × 12 × 8 grid)."""
        b, ch, nx, ny, nz = x.shape
        pad = F.pad(x, (1, 1, 1, 1, 1, 1), mode="replicate").permute(0, 2, 3, 4, 1).contiguous()
        shifted = [
            pad[:, i : i + nx, j : j + ny, k : k + nz]
            for i in range(3)
            for j in range(3)
            for k in range(3)
        ]
        return torch.stack(shifted, dim=-2).reshape(b, nx, ny * nz, 27, ch)

    def design(self, x: torch.Tensor, coords: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        """Design rows (B, X, Y·Z, 27·C + 3 + cond): the stencil (feature c·27 + neighbour), the
        position, the control."""
        b, _, *grid = x.shape
        n = grid[1] * grid[2]
        st = self.stencil(x).transpose(-1, -2).flatten(-2)
        pos = coords.permute(1, 2, 3, 0).reshape(1, grid[0], n, 3).expand(b, -1, -1, -1)
        cond = c[:, None, None, :].expand(-1, grid[0], n, -1)
        return torch.cat([st, pos, cond], dim=-1)

    def forward(self, x: torch.Tensor, coords: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        """The design rows times the weights, by parts (the same sums as ``design`` @ weight):
        the stencil as one grouped 2D convolution over each box's (y, z), a group per layer
        along x reading its three-layer slab, the position's and the control's terms added
        without copying them into every row. Stacking the stencil first and multiplying took
        2.1 ms a call on the default grid against 0.8 ms (``benchmarks/ridge_stencil.py``,
        BENCHMARKS.md)."""
        b, ch, nx, ny, nz = x.shape
        d, outs = 27 * ch, self.weight.shape[-1]
        pad = F.pad(x, (1, 1, 1, 1, 1, 1), mode="replicate")
        slabs = (
            pad.unfold(2, 3, 1).permute(0, 2, 1, 5, 3, 4).reshape(b, nx * ch * 3, ny + 2, nz + 2)
        )
        pos = coords.permute(1, 2, 3, 0)  # X, Y, Z, 3
        out = x.new_empty(b, nx, outs, ny, nz)
        for k, (y0, y1, z0, z1) in enumerate(self.boxes):
            w = self.weight[:, k]
            # weight row c·27 + 9i + 3j + k → conv kernel (layer·outputs, c·3 + i, j, k)
            kernel = w[:, :d].view(nx, ch, 3, 3, 3, outs).permute(0, 5, 1, 2, 3, 4)
            kernel = kernel.reshape(nx * outs, ch * 3, 3, 3)
            part = F.conv2d(slabs[:, :, y0 : y1 + 2, z0 : z1 + 2], kernel, groups=nx)
            part = part.view(b, nx, outs, y1 - y0, z1 - z0)
            lin = torch.einsum("xyzp,xpo->xoyz", pos[:, y0:y1, z0:z1], w[:, d : d + 3])
            lin = lin + self.bias[:, k, :, None, None]
            ctl = torch.einsum("bc,xco->bxo", c, w[:, d + 3 :])[..., None, None]
            out[:, :, :, y0:y1, z0:z1] = part + lin[None] + ctl
        return out.permute(0, 2, 1, 3, 4)


def band_boxes(
    grid: tuple[int, int, int], y_bands: tuple[int, ...], z_bands: tuple[int, ...]
) -> list[tuple[int, int, int, int]]:
    """The (y0, y1, z0, z1) boxes of bins cut by the band edges ``y_bands`` and ``z_bands``
    (inner edges, increasing; none: one box)."""
    out = []
    ys = [0, *y_bands, grid[1]]
    zs = [0, *z_bands, grid[2]]
    for edges, n, axis in ((ys, grid[1], "y"), (zs, grid[2], "z")):
        if any(b <= a for a, b in itertools.pairwise(edges)) or edges[-1] != n:
            raise ValueError(
                f"{axis} band edges must increase within 1..{n - 1}, got {edges[1:-1]}"
            )
    for y0, y1 in itertools.pairwise(ys):
        for z0, z1 in itertools.pairwise(zs):
            out.append((y0, y1, z0, z1))
    return out


def _conv(cin: int, cout: int, k: int = 3, stride: int = 1) -> nn.Sequential:
    pad = (k - 1) // 2 if stride == 1 else 0
    return nn.Sequential(Conv3d(cin, cout, k, stride=stride, padding=pad), nn.GELU())


class EvolutionUNet(nn.Module):
    """A small 3D U-Net (two stride-2 levels, skips) on the channels, the bin positions and the
    broadcast blade control; its last layer starts at zero, so training starts from advection."""

    def __init__(self, channels: int, cond: int, outputs: int, width: int = 8) -> None:
        super().__init__()
        w = width
        self.e0 = nn.Sequential(_conv(channels + cond + 3, w, 1), _conv(w, w))
        self.e1 = nn.Sequential(_conv(w, 2 * w, 2, 2), _conv(2 * w, 2 * w))
        self.e2 = nn.Sequential(_conv(2 * w, 2 * w, 2, 2), _conv(2 * w, 2 * w))
        self.d1 = _conv(4 * w, 2 * w)
        self.d0 = _conv(3 * w, w)
        self.out = Conv3d(w, outputs, 1)
        nn.init.zeros_(self.out.weight)
        assert self.out.bias is not None
        nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor, coords: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        b, grid = x.shape[0], x.shape[2:]
        cond = c[:, :, None, None, None].expand(-1, -1, *grid)
        h0 = self.e0(torch.cat([x, cond, coords.expand(b, -1, -1, -1, -1)], dim=1))
        h1 = self.e1(pad_even(h0))
        h2 = self.e2(pad_even(h1))
        u1 = self.d1(torch.cat([resize_trilinear(h2, h1.shape[2:]), h1], dim=1))
        u0 = resize_trilinear(u1, grid)
        return self.out(self.d0(torch.cat([u0, h0], dim=1)))


class DynamicsModel(nn.Module):
    """Raw store arrays → the fields of the next ``horizon`` rows, normalisation included.

    ``forward(velocity (B, H, X, Y, Z, 3) m/s, density (B, H, X, Y, Z) kg/m³, blade_velocity
    (B, H + m, 3) m/s)`` → velocity (B, m, X, Y, Z, 3) m/s (world frame) and density
    (B, m, X, Y, Z) kg/m³; float32, rows oldest first. ``row_dt`` (s) and ``bin_size`` (m) are
    those of the training stores: the frame shift per row depends on them.
    """

    coords: torch.Tensor
    chan_mean: torch.Tensor
    chan_std: torch.Tensor
    cond_mean: torch.Tensor
    cond_std: torch.Tensor
    res_std: torch.Tensor
    v_lo: torch.Tensor
    v_hi: torch.Tensor
    rho_hi: torch.Tensor

    def __init__(
        self,
        kind: str,
        grid: tuple[int, int, int],
        history: int,
        horizon: int,
        row_dt: float,
        bin_size: tuple[float, float, float],
        width: int = 8,
        y_bands: tuple[int, ...] = (),
        z_bands: tuple[int, ...] = (),
        momentum: bool = False,
    ) -> None:
        super().__init__()
        if kind not in DYNAMICS_MODELS:
            raise ValueError(f"dynamics model must be one of {list(DYNAMICS_MODELS)}, got {kind!r}")
        if history < 1 or horizon < 1:
            raise ValueError(f"history and horizon must be >= 1, got {history} and {horizon}")
        self.kind = kind
        self.grid: tuple[int, int, int] = (int(grid[0]), int(grid[1]), int(grid[2]))
        self.history, self.horizon, self.width = int(history), int(horizon), int(width)
        self.y_bands = tuple(int(e) for e in y_bands)
        self.z_bands = tuple(int(e) for e in z_bands)
        self.row_dt = float(row_dt)
        self.bin_size: tuple[float, float, float] = (
            float(bin_size[0]),
            float(bin_size[1]),
            float(bin_size[2]),
        )
        self.momentum = bool(momentum)
        channels = self.row_channels * (self.history + self.horizon)
        cond = 3 * (self.history + self.horizon)
        outputs = FIELD_CHANNELS * self.horizon
        self.register_buffer("coords", coordinates(self.grid), persistent=False)
        for name, n, value in (
            ("chan_mean", channels, 0.0),
            ("chan_std", channels, 1.0),
            ("cond_mean", cond, 0.0),
            ("cond_std", cond, 1.0),
            ("res_std", FIELD_CHANNELS, 1.0),
            ("v_lo", 3, -math.inf),
            ("v_hi", 3, math.inf),
            ("rho_hi", 1, math.inf),
        ):
            self.register_buffer(name, torch.full((n,), value))
        self.net: nn.Module | None = None
        if kind == "ridge":
            self.net = RidgeStencil(channels, cond, outputs, self.grid, self.y_bands, self.z_bands)
        elif kind == "unet":
            self.net = EvolutionUNet(channels, cond, outputs, self.width)

    def spec(self) -> dict[str, Any]:
        """What it takes to rebuild this model before loading its state dict."""
        return {
            "kind": self.kind,
            "grid": list(self.grid),
            "history": self.history,
            "horizon": self.horizon,
            "row_dt": self.row_dt,
            "bin_size": list(self.bin_size),
            "width": self.width,
            "y_bands": list(self.y_bands),
            "z_bands": list(self.z_bands),
            "momentum": self.momentum,
        }

    def base(
        self, velocity: torch.Tensor, density: torch.Tensor, blade_velocity: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The last row carried m rows ahead by advection: (B, m, …, 3) and (B, m, …)."""
        v, rho = velocity[:, -1], density[:, -1]
        vs, rhos = [], []
        for j in range(self.horizon):
            rho, v = advect(rho, v, blade_velocity[:, self.history + j], self.row_dt, self.bin_size)
            vs.append(v)
            rhos.append(rho)
        return torch.stack(vs, 1), torch.stack(rhos, 1)

    @property
    def row_channels(self) -> int:
        """Input channels per row: :data:`FIELD_CHANNELS`, or :data:`MOMENTUM_CHANNELS`."""
        return MOMENTUM_CHANNELS if self.momentum else FIELD_CHANNELS

    def channels(
        self, velocity: torch.Tensor, density: torch.Tensor, blade_velocity: torch.Tensor
    ) -> torch.Tensor:
        """(B, C·R, X, Y, Z) density and velocity relative to the blade of R rows (and with
        ``momentum`` the momentum density relative to the blade over :data:`MOMENTUM_DENSITY`),
        C = :attr:`row_channels`, with ``blade_velocity`` (B, R, 3) the blade velocity of each
        row."""
        rel = velocity - blade_velocity[:, :, None, None, None, :]
        parts = [density.unsqueeze(-1), rel]
        if self.momentum:
            parts.append(rel * (density.unsqueeze(-1) / MOMENTUM_DENSITY))
        ch = torch.cat(parts, dim=-1)  # B, R, X, Y, Z, C
        return ch.permute(0, 1, 5, 2, 3, 4).flatten(1, 2)

    def inputs(
        self,
        velocity: torch.Tensor,
        density: torch.Tensor,
        blade_velocity: torch.Tensor,
        base: tuple[torch.Tensor, torch.Tensor],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised channels (B, 4(H + m), X, Y, Z) and blade control (B, 3(H + m))."""
        x = torch.cat(
            [
                self.channels(velocity, density, blade_velocity[:, : self.history]),
                self.channels(base[0], base[1], blade_velocity[:, self.history :]),
            ],
            dim=1,
        )
        x = (x - self.chan_mean[None, :, None, None, None]) / self.chan_std[
            None, :, None, None, None
        ]
        c = (blade_velocity.flatten(1) - self.cond_mean) / self.cond_std
        return x, c

    def check(
        self, velocity: torch.Tensor, density: torch.Tensor, blade_velocity: torch.Tensor
    ) -> None:
        """Refuse arrays whose shapes do not fit this model (grid, history, horizon)."""
        from dozerlab.runtime import DozerlabError

        b, h, m = density.shape[0], self.history, self.horizon
        expected = {
            "velocity": (b, h, *self.grid, 3),
            "density": (b, h, *self.grid),
            "blade_velocity": (b, h + m, 3),
        }
        got = {
            "velocity": velocity.shape,
            "density": density.shape,
            "blade_velocity": blade_velocity.shape,
        }
        for k, shape in expected.items():
            if tuple(got[k]) != shape:
                raise DozerlabError(
                    f"input '{k}' has shape {tuple(got[k])}, expected {shape}: the model takes "
                    f"history = {h} rows on a {self.grid} grid and predicts horizon = {m} rows "
                    "(blade_velocity: the H known rows and the m rows to predict)"
                )

    def forward(
        self, velocity: torch.Tensor, density: torch.Tensor, blade_velocity: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        self.check(velocity, density, blade_velocity)
        if self.net is None:
            m = self.horizon
            return (
                velocity[:, -1:].expand(-1, m, -1, -1, -1, -1).clone(),
                density[:, -1:].expand(-1, m, -1, -1, -1).clone(),
            )
        base = self.base(velocity, density, blade_velocity)
        x, c = self.inputs(velocity, density, blade_velocity, base)
        return self.correct(base, self.net(x, self.coords, c))

    def correct(
        self, base: tuple[torch.Tensor, torch.Tensor], residual: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Base fields plus the normalised residual (B, 4m, X, Y, Z), kept within the range of
        the training fields (density in [0, ρ_max], each velocity component in [min, max]): a
        rollout fed its own output stays bounded."""
        b, m = residual.shape[0], self.horizon
        r = (
            residual.view(b, m, FIELD_CHANNELS, *self.grid)
            * self.res_std[None, None, :, None, None, None]
        )
        density = torch.minimum((base[1] + r[:, :, 0]).clamp_min(0), self.rho_hi)
        velocity = base[0] + r[:, :, 1:].permute(0, 1, 3, 4, 5, 2)
        return torch.maximum(torch.minimum(velocity, self.v_hi), self.v_lo), density
