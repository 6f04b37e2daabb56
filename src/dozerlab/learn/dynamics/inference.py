"""The ridge evolution model's forward for one window at a time, as the reduced loop calls it.

:class:`RidgeInference` computes what :meth:`DynamicsModel.forward
<dozerlab.learn.dynamics.models.DynamicsModel.forward>` computes for a ``ridge`` model, to
float32 round-off, in one pass each for the advection, the normalised stencil slabs and the
correction, around the stencil's grouped convolutions (torch's, the one costly part). The
terms that do not change between calls — the position's and bias's, the kernels — are made
once. On the default grid a call takes 1.1–1.8 ms against the module's 2.6–2.8 ms, most of
which were the many small tensor operations around the convolutions (BENCHMARKS.md, "The
ridge's inference in the loop").
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch.nn import functional as F

from dozerlab.learn.dynamics.advection import EMPTY_DENSITY
from dozerlab.learn.dynamics.models import FIELD_CHANNELS, DynamicsModel, RidgeStencil


@njit(cache=True)
def advect_row(rho, vel, shift, scale):  # pragma: no cover - compiled
    """:func:`dozerlab.learn.dynamics.advection.advect` of one row: density ``rho`` (X, Y, Z)
    kg/m³ and velocity ``vel`` (X, Y, Z, 3) m/s carried one row along v·``scale`` − ``shift``
    (bins per row; ``scale`` (3,) = Δt / bin size, ``shift`` (3,) the grid's own move).
    Returns the new density and velocity (float32)."""
    nx, ny, nz = rho.shape
    q = np.empty((4, nx, ny, nz), np.float32)
    u = np.empty((3, nx, ny, nz), np.float32)
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                r = rho[i, j, k]
                q[0, i, j, k] = r
                for a in range(3):
                    q[a + 1, i, j, k] = r * vel[i, j, k, a]
                    u[a, i, j, k] = vel[i, j, k, a] * scale[a] - shift[a]
    new = q.copy()
    dims = (nx, ny, nz)
    for a in range(3):
        n = dims[a]
        for i in range(nx if a != 0 else 1):
            for j in range(ny if a != 1 else 1):
                for k in range(nz if a != 2 else 1):
                    # the faces along axis a of the line through (i, j, k), ghost bins replicated
                    for f in range(n + 1):
                        lo, hi = max(f - 1, 0), min(f, n - 1)
                        il, jl, kl = i, j, k
                        ih, jh, kh = i, j, k
                        if a == 0:
                            il, ih = lo, hi
                        elif a == 1:
                            jl, jh = lo, hi
                        else:
                            kl, kh = lo, hi
                        rl, rh = q[0, il, jl, kl], q[0, ih, jh, kh]
                        ul, uh = u[a, il, jl, kl], u[a, ih, jh, kh]
                        m = rl + rh
                        if m > 0:
                            uf = (rl * ul + rh * uh) / max(m, np.float32(1e-30))
                        else:
                            uf = np.float32(0.5) * (ul + uh)
                        up, dn = max(uf, np.float32(0.0)), min(uf, np.float32(0.0))
                        for c in range(4):
                            flux = up * q[c, il, jl, kl] + dn * q[c, ih, jh, kh]
                            if f > 0:  # out of the bin before the face
                                new[c, il, jl, kl] -= flux
                            if f < n:  # into the bin after it
                                new[c, ih, jh, kh] += flux
    rho_new = np.empty((nx, ny, nz), np.float32)
    v_new = np.zeros((nx, ny, nz, 3), np.float32)
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                r = max(new[0, i, j, k], np.float32(0.0))
                rho_new[i, j, k] = r
                if r > EMPTY_DENSITY:
                    for a in range(3):
                        v_new[i, j, k, a] = new[a + 1, i, j, k] / r
    return rho_new, v_new


@njit(cache=True)
def stencil_slabs(
    hist_rho, hist_v, blade_v, base_rho, base_v, mean, std, boxes
):  # pragma: no cover - compiled
    """The normalised channels of H history rows (``hist_rho`` (H, X, Y, Z), ``hist_v``
    (H, X, Y, Z, 3)) and m advected rows (``base_rho``, ``base_v``), velocities relative to
    ``blade_v`` (H + m, 3), as :class:`RidgeStencil`'s slabs of each of ``boxes`` (K, 4)
    (y0, y1, z0, z1), back to back in one float32 buffer: box k's is (X·C·3, y1 − y0 + 2,
    z1 − z0 + 2), slab x·3C + 3c + i the layer x + i − 1 of channel c, edges replicated (one
    contiguous input per convolution: a view into one padded grid cost 40 % more)."""
    h, nx, ny, nz = hist_rho.shape
    rows = h + base_rho.shape[0]
    ch = FIELD_CHANNELS * rows
    pad = np.empty((ch, nx + 2, ny + 2, nz + 2), np.float32)
    for c in range(ch):
        row, comp = c // FIELD_CHANNELS, c % FIELD_CHANNELS
        for i in range(nx + 2):
            xs = min(max(i - 1, 0), nx - 1)
            for j in range(ny + 2):
                ys = min(max(j - 1, 0), ny - 1)
                for k in range(nz + 2):
                    zs = min(max(k - 1, 0), nz - 1)
                    if row < h:
                        if comp == 0:
                            val = hist_rho[row, xs, ys, zs]
                        else:
                            val = hist_v[row, xs, ys, zs, comp - 1] - blade_v[row, comp - 1]
                    elif comp == 0:
                        val = base_rho[row - h, xs, ys, zs]
                    else:
                        val = base_v[row - h, xs, ys, zs, comp - 1] - blade_v[row, comp - 1]
                    pad[c, i, j, k] = (val - mean[c]) / std[c]
    size = 0
    for b in range(boxes.shape[0]):
        size += nx * ch * 3 * (boxes[b, 1] - boxes[b, 0] + 2) * (boxes[b, 3] - boxes[b, 2] + 2)
    out = np.empty(size, np.float32)
    p = 0
    for b in range(boxes.shape[0]):
        y0, y1, z0, z1 = boxes[b, 0], boxes[b, 1], boxes[b, 2], boxes[b, 3]
        for x in range(nx):
            for c in range(ch):
                for i in range(3):
                    for j in range(y0, y1 + 2):
                        for k in range(z0, z1 + 2):
                            out[p] = pad[c, x + i, j, k]
                            p += 1
    return out


@njit(cache=True)
def finish(
    conv, const, ctl_w, cond, box_of, res_std, base_rho, base_v, rho_hi, v_lo, v_hi
):  # pragma: no cover - compiled
    """The stencil's sums ``conv`` (X, 4m, Y, Z) plus its constant terms ``const`` (same
    shape: position and bias) and control terms (``ctl_w`` (X, boxes, cond, 4m) times the
    normalised control ``cond``; ``box_of`` (Y, Z) each bin's box), in residual spreads
    ``res_std`` (4,), added to the advected rows and kept within the training range, as
    :meth:`DynamicsModel.correct`. Returns velocity (m, X, Y, Z, 3) and density (m, X, Y, Z)."""
    nx, outs, ny, nz = conv.shape
    m = outs // FIELD_CHANNELS
    nb, nc = ctl_w.shape[1], ctl_w.shape[2]
    ctl = np.zeros((nx, nb, outs), np.float32)
    for x in range(nx):
        for b in range(nb):
            for o in range(outs):
                acc = np.float32(0.0)
                for q in range(nc):
                    acc += cond[q] * ctl_w[x, b, q, o]
                ctl[x, b, o] = acc
    rho = np.empty((m, nx, ny, nz), np.float32)
    vel = np.empty((m, nx, ny, nz, 3), np.float32)
    for x in range(nx):
        for y in range(ny):
            for z in range(nz):
                b = box_of[y, z]
                for j in range(m):
                    f = FIELD_CHANNELS * j
                    r = (conv[x, f, y, z] + const[x, f, y, z] + ctl[x, b, f]) * res_std[0]
                    rho[j, x, y, z] = min(max(base_rho[j, x, y, z] + r, np.float32(0.0)), rho_hi)
                    for a in range(3):
                        o = f + 1 + a
                        r = (conv[x, o, y, z] + const[x, o, y, z] + ctl[x, b, o]) * res_std[1 + a]
                        vel[j, x, y, z, a] = max(min(base_v[j, x, y, z, a] + r, v_hi[a]), v_lo[a])
    return vel, rho


def _numpy(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), np.float32)


class RidgeInference:
    """A ``ridge`` :class:`DynamicsModel`'s forward for one window, NumPy in and out.

    ``predict(velocity (H, X, Y, Z, 3) m/s, density (H, X, Y, Z) kg/m³, blade_velocity
    (H + m, 3) m/s)`` → velocity (m, X, Y, Z, 3) and density (m, X, Y, Z), float32: the module's
    forward on the same window (batch of one) to float32 round-off. The model's weights are
    read once: build it again after changing them.
    """

    def __init__(self, model: DynamicsModel) -> None:
        net = model.net
        if model.kind != "ridge" or not isinstance(net, RidgeStencil):
            raise ValueError(f"RidgeInference needs a ridge model, got {model.kind!r}")
        self.history, self.horizon, self.grid = model.history, model.horizon, model.grid
        nx, ny, nz = self.grid
        ch = FIELD_CHANNELS * (self.history + self.horizon)
        d, outs = 27 * ch, FIELD_CHANNELS * self.horizon
        self.boxes = list(net.boxes)
        self.box_array = np.array(self.boxes, np.int64).reshape(-1, 4)
        with torch.no_grad():
            w, bias = net.weight.detach().float().cpu(), net.bias.detach().float().cpu()
            pos = model.coords.cpu().permute(1, 2, 3, 0)
            self.kernels = [
                w[:, k, :d]
                .reshape(nx, ch, 3, 3, 3, outs)
                .permute(0, 5, 1, 2, 3, 4)
                .reshape(nx * outs, ch * 3, 3, 3)
                .contiguous()
                for k in range(len(self.boxes))
            ]
            const = torch.zeros(nx, outs, ny, nz)
            box_of = np.zeros((ny, nz), np.int64)
            for k, (y0, y1, z0, z1) in enumerate(self.boxes):
                lin = torch.einsum("xyzp,xpo->xoyz", pos[:, y0:y1, z0:z1], w[:, k, d : d + 3])
                const[:, :, y0:y1, z0:z1] = lin + bias[:, k, :, None, None]
                box_of[y0:y1, z0:z1] = k
        self.const, self.box_of = _numpy(const), box_of
        self.ctl_w = _numpy(w[:, :, d + 3 :])
        self.chan_mean, self.chan_std = _numpy(model.chan_mean), _numpy(model.chan_std)
        self.cond_mean, self.cond_std = _numpy(model.cond_mean), _numpy(model.cond_std)
        self.res_std = _numpy(model.res_std)
        self.v_lo, self.v_hi = _numpy(model.v_lo), _numpy(model.v_hi)
        self.rho_hi = np.float32(model.rho_hi[0])
        self.scale = np.array(
            [model.row_dt / b for b in model.bin_size], np.float32
        )  # bins per row per m/s
        # compile the kernels (or load them from numba's cache) now, not in the first call
        h, m = self.history, self.horizon
        self.predict(
            np.zeros((h, nx, ny, nz, 3), np.float32),
            np.zeros((h, nx, ny, nz), np.float32),
            np.zeros((h + m, 3), np.float32),
        )

    def predict(
        self, velocity: np.ndarray, density: np.ndarray, blade_velocity: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        h, m = self.history, self.horizon
        nx, ny, nz = self.grid
        v = np.ascontiguousarray(velocity, np.float32)
        rho = np.ascontiguousarray(density, np.float32)
        vb = np.ascontiguousarray(blade_velocity, np.float32)
        base_rho = np.empty((m, nx, ny, nz), np.float32)
        base_v = np.empty((m, nx, ny, nz, 3), np.float32)
        r, u = rho[-1], v[-1]
        for j in range(m):
            r, u = advect_row(r, u, vb[h + j] * self.scale, self.scale)
            base_rho[j], base_v[j] = r, u
        buf = torch.from_numpy(
            stencil_slabs(
                rho, v, vb, base_rho, base_v, self.chan_mean, self.chan_std, self.box_array
            )
        )
        conv = np.empty((nx, FIELD_CHANNELS * m, ny, nz), np.float32)
        at = 0
        with torch.no_grad():
            for kernel, (y0, y1, z0, z1) in zip(self.kernels, self.boxes, strict=True):
                shape = (1, kernel.shape[1] * nx, y1 - y0 + 2, z1 - z0 + 2)
                size = shape[1] * shape[2] * shape[3]
                part = F.conv2d(buf[at : at + size].view(shape), kernel, groups=nx)
                conv[:, :, y0:y1, z0:z1] = part.view(nx, -1, y1 - y0, z1 - z0).numpy()
                at += size
        cond = (vb.reshape(-1) - self.cond_mean) / self.cond_std
        return finish(
            conv,
            self.const,
            self.ctl_w,
            cond,
            self.box_of,
            self.res_std,
            base_rho,
            base_v,
            self.rho_hi,
            self.v_lo,
            self.v_hi,
        )
