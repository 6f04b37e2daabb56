"""The force/torque models: ``linear`` (ridge), ``mlp``, ``cnn`` (the thesis's) and ``unet``.

Every model is a :class:`ForceModel`: raw store arrays in, force (N) and torque (N·m) out. It
turns the fields into physically motivated channels per history step — the velocity relative
to the blade (3), the density (1), the momentum density relative to the blade ρ(v − v_b) (3),
which is zero in empty bins, and the momentum density ρv (3) — and, from the second history
step on, the change of density and momentum density since the step before (4). The blade's
force is, by the momentum balance of the material in front of it, largely the rate of change
of that momentum: on the 10 cm-grain sweep a ridge fit of per-column mass and momentum with
their one-step changes cut the held-out force error from 27 % to 19 % (BENCHMARKS.md). The channels
are normalised with statistics of the training points and passed with the normalised blade
velocity (the conditioning input) to a backbone that predicts the normalised targets. The
normalisation lives in buffers of the module, so a saved state dict is the whole model.

With ``contact`` (``learn.contact``) a model knows two things about the blade's contact that the
fields in its frame do not say. The conditioning gains the **pushing gate**
(:func:`pushing_gate`): the share of the blade's motion that is horizontal times the density
against its face; the linear model fits its terms once plain and once times the gate, so a blade
moving straight up or down, or with nothing against its face, gets its own weights (no training
run had such rows: the unseen trench's path has them, BENCHMARKS.md "Unseen terrain"). And the
pushing force is **one-sided**: grains push on the blade's faces, they cannot pull it (no
cohesion), so the predicted ``force_x`` is clipped at 0 (every training row of the default sweep
has ``force_x`` ≤ 0 N).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

#: Channels of each history step: v − v_b (3), ρ (1), ρ(v − v_b) (3), ρv (3).
CHANNELS_PER_STEP = 10
#: Channels of the change since the step before, for every step but the oldest: Δρ (1), Δ(ρv) (3).
CHANNELS_PER_CHANGE = 4
OUTPUTS = 6
#: Conditioning entries after the blade velocities of a model with contact inputs: the pushing gate.
CONTACT_ENTRIES = 1


def n_channels(history: int) -> int:
    """Input channels of a model with ``history`` steps."""
    return CHANNELS_PER_STEP * history + CHANNELS_PER_CHANGE * (history - 1)


#: Parity of each target under the mirror y → −y (bed and blade are symmetric in y):
#: force_y and the torques about the x and z axes (axial vectors) change sign.
TARGET_PARITY = (1.0, -1.0, 1.0, -1.0, 1.0, -1.0)


def channel_parity(history: int, contact: bool = False) -> tuple[list[float], list[float]]:
    """Parity under the mirror y → −y of each input channel and each conditioning entry of a
    model with ``history`` steps (and the pushing gate, even, with ``contact``): the y
    components of velocities and momenta are odd."""
    step = [1.0, -1.0, 1.0, 1.0, 1.0, -1.0, 1.0, 1.0, -1.0, 1.0]  # v−v_b, ρ, ρ(v−v_b), ρv
    change = [1.0, 1.0, -1.0, 1.0]  # Δρ, Δ(ρv)
    cond = [1.0, -1.0, 1.0] * history + [1.0] * (CONTACT_ENTRIES if contact else 0)
    return step * history + change * (history - 1), cond


def pushing_gate(density: torch.Tensor, blade_velocity: torch.Tensor) -> torch.Tensor:
    """(B,) the blade's horizontal share of its motion, max(v_bx, 0) / |v_b| (0 at rest), times
    the mean density (kg/m³) of the bins against its face (the first bins along x), at the
    newest step of density (B, H, X, Y, Z) and blade_velocity (B, H, 3).

    The resistance to a blade comes from pushing into the material ahead: it is small when the
    blade moves straight up or down (the trench's path, ``force_x`` −0.5 to 0 kN there) or when
    nothing lies against its face.
    """
    vb = blade_velocity[:, -1]
    speed = torch.linalg.vector_norm(vb, dim=1)
    share = torch.where(speed > 0, vb[:, 0].clamp(min=0.0) / speed.clamp(min=1e-12), 0.0)
    return share * density[:, -1, 0].mean(dim=(1, 2))


class LinearHead(nn.Module):
    """Ridge regression on per-(x, z)-column features, equivariant under the mirror y → −y
    (fitted in closed form).

    The conditioning is 3 entries per history step, then the pushing gate g when the model has
    contact inputs (``cond`` = 3H + 1): then the even targets are fitted on the even features
    f and on g·f and g, a linear model whose weights depend on g (g is even, the odd fit is
    unchanged).

    The force on a blade as wide as the sampling volume is a sum over the material across
    it, so each channel enters through its sum over y and its first moment Σ y·x (the
    lateral imbalance, which drives force_y and the x/z torques). Under the mirror a feature is
    even or odd — the y-sum of an even channel or the moment of an odd one is even — and so is
    each target; even targets are fitted on the even features only and odd ones on the odd
    ones, so the prediction for a mirrored sample is exactly the mirrored prediction. Each target
    has Ny× fewer weights than in a ridge on every bin, and it generalises better (BENCHMARKS.md).
    """

    y_coord: torch.Tensor
    chan_odd: torch.Tensor
    cond_odd: torch.Tensor
    target_odd: torch.Tensor

    def __init__(self, in_channels: int, cond: int, grid: tuple[int, int, int]) -> None:
        super().__init__()
        history, extra = divmod(cond, 3)
        self.contact = extra == CONTACT_ENTRIES
        chan, cond_par = channel_parity(history, self.contact)
        if len(chan) != in_channels:
            raise ValueError(
                f"linear: {in_channels} channels do not match a history of {history} steps"
            )
        self.register_buffer(
            "y_coord", torch.linspace(-1.0, 1.0, grid[1]).view(1, 1, 1, -1, 1), persistent=False
        )
        self.register_buffer("chan_odd", torch.tensor(chan) < 0, persistent=False)
        self.register_buffer("cond_odd", torch.tensor(cond_par) < 0, persistent=False)
        self.register_buffer("target_odd", torch.tensor(TARGET_PARITY) < 0, persistent=False)
        columns, n_odd = in_channels * grid[0] * grid[2], int(self.cond_odd.sum())
        even = columns + cond - n_odd
        self.even = nn.Linear(2 * even - 1 if self.contact else even, 3)
        self.odd = nn.Linear(columns + n_odd, 3)

    def designs(self, x: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The even and odd design-matrix rows, (B, D_even) and (B, D_odd), of inputs
        x (B, C, X, Y, Z) and c (B, cond)."""
        total, moment = x.sum(dim=3), (x * self.y_coord).sum(dim=3)  # B, C, X, Z
        odd = self.chan_odd[None, :, None, None]
        even_f = torch.where(odd, moment, total).flatten(1)
        odd_f = torch.where(odd, total, moment).flatten(1)
        odd_design = torch.cat([odd_f, c[:, self.cond_odd]], dim=1)
        if not self.contact:
            return torch.cat([even_f, c[:, ~self.cond_odd]], dim=1), odd_design
        plain = torch.cat(
            [even_f, c[:, :-CONTACT_ENTRIES][:, ~self.cond_odd[:-CONTACT_ENTRIES]]], dim=1
        )
        gate = c[:, -1:]
        return torch.cat([plain, gate * plain, gate], dim=1), odd_design

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        even, odd = self.designs(x, c)
        out = torch.empty(x.shape[0], OUTPUTS, dtype=x.dtype, device=x.device)
        out[:, ~self.target_odd] = self.even(even)
        out[:, self.target_odd] = self.odd(odd)
        return out


class MLP(nn.Module):
    """Multilayer perceptron on the flattened channels plus the conditioning."""

    def __init__(
        self, in_channels: int, cond: int, grid: tuple[int, int, int], hidden: int = 256
    ) -> None:
        super().__init__()
        d = in_channels * grid[0] * grid[1] * grid[2] + cond
        self.net = nn.Sequential(
            nn.Linear(d, hidden),
            nn.GELU(),
            nn.Linear(hidden, hidden // 2),
            nn.GELU(),
            nn.Linear(hidden // 2, OUTPUTS),
        )

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([x.flatten(1), c], dim=1))


#: im2col columns (input channels × kernel volume × output bins) from which oneDNN's convolution
#: beats torch's im2col path for one sample: below, and for 1³ kernels (no im2col), its ≈80 µs
#: of weight reordering a call outweighs what it saves (``benchmarks/inference_conv.py``).
ONEDNN_COLUMNS = 100_000


class Conv3d(nn.Conv3d):
    """``nn.Conv3d`` (same parameters and state dict) that, where no gradient is asked for on
    the CPU in float32, runs its large convolutions with oneDNN directly: for the one sample at
    a time the reduced loop asks for, torch's own dispatch takes its unvectorised im2col path,
    3× slower for the larger kernels on the full grid (``benchmarks/inference_conv.py``); the
    outputs agree to float32 round-off."""

    def uses_onednn(self, x: torch.Tensor) -> bool:
        """Whether :meth:`forward` runs oneDNN's convolution on ``x`` (B, C, X, Y, Z)."""
        kernel = self.kernel_size[0] * self.kernel_size[1] * self.kernel_size[2]
        bins = x[0, 0].numel() // (self.stride[0] * self.stride[1] * self.stride[2])
        return not (
            kernel == 1
            or x.shape[1] * kernel * bins < ONEDNN_COLUMNS
            or x.device.type != "cpu"
            or x.dtype != torch.float32
            or self.padding_mode != "zeros"
            or isinstance(self.padding, str)
            or (torch.is_grad_enabled() and (x.requires_grad or self.weight.requires_grad))
            or not torch.backends.mkldnn.is_available()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.uses_onednn(x):
            return super().forward(x)
        return torch.ops.aten.mkldnn_convolution(
            x.contiguous(),
            self.weight,
            self.bias,
            self.padding,
            self.stride,
            self.dilation,
            self.groups,
        )


def _same2(cin: int, cout: int) -> nn.Sequential:
    """A 2³ convolution that keeps the grid size (TensorFlow's 'same': one extra bin at the end)."""
    return nn.Sequential(nn.ConstantPad3d((0, 1, 0, 1, 0, 1), 0.0), Conv3d(cin, cout, 2))


class ThesisCNN(nn.Module):
    """The thesis's multi-scale 3D CNN (docs/models.md): conv 8@2³; three branches (none / max-pool 2
    / max-pool 4, each then conv 8@2³), upsampled to the grid and added; conv 8@1³; FC 384;
    FC 192; output. The conditioning joins at the first fully connected layer."""

    def __init__(
        self, in_channels: int, cond: int, grid: tuple[int, int, int], width: int = 8
    ) -> None:
        super().__init__()
        self.grid = grid
        self.stem = _same2(in_channels, width)
        self.branches = nn.ModuleList(_same2(width, width) for _ in range(3))
        self.mix = Conv3d(width, width, 1)
        d = width * grid[0] * grid[1] * grid[2] + cond
        self.head = nn.Sequential(
            nn.Linear(d, 384), nn.ReLU(), nn.Linear(384, 192), nn.ReLU(), nn.Linear(192, OUTPUTS)
        )

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        h = F.relu(self.stem(x))
        out = F.relu(self.branches[0](h))
        for scale, conv in ((2, self.branches[1]), (4, self.branches[2])):
            pooled = F.max_pool3d(h, scale, scale, ceil_mode=True)
            out = out + F.interpolate(F.relu(conv(pooled)), size=self.grid, mode="nearest")
        h = F.relu(self.mix(out))
        return self.head(torch.cat([h.flatten(1), c], dim=1))


@functools.cache
def _linear_resize_matrix(n_in: int, n_out: int, dtype: torch.dtype, device: str) -> torch.Tensor:
    """(n_out, n_in) weights of 1D linear resizing, taken from ``F.interpolate`` itself (made
    outside inference mode, so training in the same process can save it for backward)."""
    with torch.inference_mode(False):
        eye = torch.eye(n_in, dtype=dtype, device=device)[:, None, :]
        out = F.interpolate(eye, size=n_out, mode="linear", align_corners=False)
        return out[:, 0, :].T.contiguous()


def resize_trilinear(x: torch.Tensor, size: tuple[int, ...] | torch.Size) -> torch.Tensor:
    """``F.interpolate(x, size, mode="trilinear", align_corners=False)`` of (B, C, X, Y, Z), equal
    to round-off, as three small matrix products: torch's own kernel took 4–10× as long on the
    CPU, forward and backward (a fifth of the U-Net's training step)."""
    nx, ny, nz = x.shape[2:]
    sx, sy, sz = (int(n) for n in size)
    ax, ay, az = (
        _linear_resize_matrix(n_in, n_out, x.dtype, str(x.device))
        for n_in, n_out in ((nx, sx), (ny, sy), (nz, sz))
    )
    x = torch.matmul(x, az.T)  # B, C, X, Y, sz
    x = torch.matmul(ay, x)  # B, C, X, sy, sz
    return torch.matmul(ax, x.flatten(3)).unflatten(3, (sy, sz))


def pad_even(x: torch.Tensor) -> torch.Tensor:
    """Pad (B, C, X, Y, Z) by one replicated bin at the end of each odd axis (for stride 2)."""
    pad = []
    for n in reversed(x.shape[2:]):
        pad += [0, n % 2]
    return F.pad(x, pad, mode="replicate") if any(pad) else x


def _block(cin: int, cout: int, k: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        Conv3d(cin, cout, k, stride=stride, padding=(k - 1) // 2 if stride == 1 else 0),
        nn.GELU(),
    )


class ForceDensityUNet(nn.Module):
    """A small 3D U-Net that predicts a force/torque density per bin and sums it over the grid.

    The force on the blade is a sum of what the material in each bin pushes on it, so the
    readout is a sum of per-bin contributions rather than a dense layer over the whole grid: it
    has few parameters (less to memorise from a handful of sweep points), and a fuller or faster
    volume adds contributions instead of landing off the training manifold, which is what
    extrapolation to deeper cuts and higher speeds asks for. Bin coordinates (blade frame) and
    the broadcast blade velocity are input channels, so a bin's contribution can depend on its
    distance to the blade and on the blade's motion; the encoder (two stride-2 levels) gives
    each bin the context of the material around it, the skips keep the local detail.
    """

    coords: torch.Tensor

    def __init__(
        self, in_channels: int, cond: int, grid: tuple[int, int, int], width: int = 16
    ) -> None:
        super().__init__()
        self.grid = grid
        axes = [torch.linspace(-1.0, 1.0, n) for n in grid]
        self.register_buffer(
            "coords", torch.stack(torch.meshgrid(*axes, indexing="ij")), persistent=False
        )
        cin = in_channels + cond + 3
        self.e0 = _block(cin, width, 1)
        self.e1 = nn.Sequential(_block(width, width, 2, stride=2), _block(width, width, 3))
        self.e2 = nn.Sequential(
            _block(width, 2 * width, 2, stride=2), _block(2 * width, 2 * width, 3)
        )
        self.d1 = _block(3 * width, width, 1)
        self.d0 = nn.Sequential(_block(2 * width, width, 1), Conv3d(width, OUTPUTS, 1))
        self.cond_head = nn.Linear(cond, OUTPUTS)

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        b = x.shape[0]
        cond = c[:, :, None, None, None].expand(-1, -1, *self.grid)
        h0 = self.e0(torch.cat([x, cond, self.coords.expand(b, -1, -1, -1, -1)], dim=1))
        h1 = self.e1(pad_even(h0))
        h2 = self.e2(pad_even(h1))
        u1 = self.d1(torch.cat([resize_trilinear(h2, h1.shape[2:]), h1], dim=1))
        u0 = resize_trilinear(u1, self.grid)
        density = self.d0(torch.cat([u0, h0], dim=1))
        return density.mean(dim=(2, 3, 4)) + self.cond_head(c)


#: One backbone per name in :data:`dozerlab.learn.names.MODEL_NAMES`, in that order.
BACKBONES: dict[str, Callable[..., nn.Module]] = {
    "linear": LinearHead,
    "mlp": MLP,
    "cnn": ThesisCNN,
    "unet": ForceDensityUNet,
}


class ForceModel(nn.Module):
    """Raw store arrays → (B, 6) force (N) and torque (N·m), normalisation included.

    ``forward(velocity (B, H, Nx, Ny, Nz, 3), density (B, H, Nx, Ny, Nz), blade_velocity
    (B, H, 3))``, float32, H = ``history`` steps oldest first. With ``contact`` the conditioning
    ends in the pushing gate and ``force_x`` is clipped at 0 (the module docstring). With
    ``blade_part`` (x0, y0, y1, z1) it reads only bins [x0:, y0:y1, :z1] of the (Nx, Ny, Nz)
    ``grid`` (:attr:`dozerlab.fields.sampling.SamplingGrid.blade_part`): the material behind,
    beside and above the blade pushes on it only through the blade part.
    """

    chan_mean: torch.Tensor
    chan_std: torch.Tensor
    cond_mean: torch.Tensor
    cond_std: torch.Tensor
    y_mean: torch.Tensor
    y_std: torch.Tensor

    def __init__(
        self,
        kind: str,
        grid: tuple[int, int, int],
        history: int = 1,
        contact: bool = False,
        blade_part: tuple[int, int, int, int] | None = None,
    ) -> None:
        super().__init__()
        if kind not in BACKBONES:
            raise ValueError(f"model must be one of {list(BACKBONES)}, got {kind!r}")
        nx, ny, nz = (int(n) for n in grid)
        self.kind, self.grid, self.history = kind, (nx, ny, nz), int(history)
        self.contact = bool(contact)
        part = (0, 0, ny, nz) if blade_part is None else tuple(int(n) for n in blade_part)
        if len(part) != 4 or not (
            0 <= part[0] < nx and 0 <= part[1] < part[2] <= ny and 0 < part[3] <= nz
        ):
            raise ValueError(f"blade_part {blade_part} is not a part of the {self.grid} grid")
        x0, y0, y1, z1 = part
        self.blade_part = (x0, y0, y1, z1)
        c_in = n_channels(self.history)
        cond = 3 * self.history + (CONTACT_ENTRIES if self.contact else 0)
        self.backbone = BACKBONES[kind](c_in, cond, (nx - x0, y1 - y0, z1))
        for name, n in (("chan_mean", c_in), ("cond_mean", cond), ("y_mean", OUTPUTS)):
            self.register_buffer(name, torch.zeros(n))
        for name, n in (("chan_std", c_in), ("cond_std", cond), ("y_std", OUTPUTS)):
            self.register_buffer(name, torch.ones(n))

    def spec(self) -> dict[str, Any]:
        """What it takes to rebuild this model before loading its state dict."""
        return {
            "kind": self.kind,
            "grid": list(self.grid),
            "history": self.history,
            "contact": self.contact,
            "blade_part": list(self.blade_part),
        }

    def raw_features(
        self, velocity: torch.Tensor, density: torch.Tensor, blade_velocity: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Unnormalised channels (B, n_channels(H), X, Y, Z) and conditioning (B, 3H), with
        ``contact`` (B, 3H + 1): the pushing gate last.

        Channels: the H steps' own channels (oldest first), then the H − 1 changes. Written in
        place into one tensor (16× faster than concatenating channel-last parts and permuting),
        so the inputs must not require gradients. Only the blade part is read."""
        x0, y0, y1, z1 = self.blade_part
        velocity, density = velocity[:, :, x0:, y0:y1, :z1], density[:, :, x0:, y0:y1, :z1]
        b, h, nx, ny, nz = density.shape
        out = velocity.new_empty((b, n_channels(h), nx, ny, nz))
        steps = out[:, : CHANNELS_PER_STEP * h].view(b, h, CHANNELS_PER_STEP, nx, ny, nz)
        vel = velocity.permute(0, 1, 5, 2, 3, 4)
        rho = density.unsqueeze(2)
        torch.sub(vel, blade_velocity[..., None, None, None], out=steps[:, :, 0:3])
        steps[:, :, 3:4] = rho
        torch.mul(steps[:, :, 0:3], rho, out=steps[:, :, 4:7])
        torch.mul(vel, rho, out=steps[:, :, 7:10])
        if h > 1:
            changes = out[:, CHANNELS_PER_STEP * h :].view(
                b, h - 1, CHANNELS_PER_CHANGE, nx, ny, nz
            )
            for dst, src in ((slice(0, 1), slice(3, 4)), (slice(1, 4), slice(7, 10))):
                torch.sub(steps[:, 1:, src], steps[:, :-1, src], out=changes[:, :, dst])
        cond = blade_velocity.reshape(b, -1)
        if self.contact:
            cond = torch.cat([cond, pushing_gate(density, blade_velocity)[:, None]], dim=1)
        return out, cond

    def inputs(
        self, velocity: torch.Tensor, density: torch.Tensor, blade_velocity: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised backbone inputs."""
        x, c = self.raw_features(velocity, density, blade_velocity)
        x.sub_(self.chan_mean[None, :, None, None, None]).div_(
            self.chan_std[None, :, None, None, None]
        )
        return x, (c - self.cond_mean) / self.cond_std

    def normalized(
        self, velocity: torch.Tensor, density: torch.Tensor, blade_velocity: torch.Tensor
    ) -> torch.Tensor:
        """(B, 6) predictions in units of the training targets' standard deviation."""
        return self.backbone(*self.inputs(velocity, density, blade_velocity))

    def forward(
        self, velocity: torch.Tensor, density: torch.Tensor, blade_velocity: torch.Tensor
    ) -> torch.Tensor:
        out = self.normalized(velocity, density, blade_velocity) * self.y_std + self.y_mean
        if self.contact:
            # one-sided contact: the grains push the blade back, they cannot pull it
            out = torch.cat([out[:, :1].clamp(max=0.0), out[:, 1:]], dim=1)
        return out
