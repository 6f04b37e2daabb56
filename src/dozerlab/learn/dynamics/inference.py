"""The ridge evolution model's forward for one window at a time, as the reduced loop calls it.

:class:`RidgeInference` computes what :meth:`DynamicsModel.forward
<dozerlab.learn.dynamics.models.DynamicsModel.forward>` computes for a ``ridge`` model, to
float32 round-off, in two compiled passes: the advection, then the stencil's sums with the
correction and clamps (:func:`correct_rows`). The terms that do not change between calls (the
position's and bias's, the weights in the order the sums read them) are made once. On the
default sweep's ridge (momentum channels, three rows a call) a call takes 1.63–1.64 ms against
8.7–8.9 ms through the module (BENCHMARKS.md, "The ridge's sums, three layers a pass").
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from dozerlab.learn.dynamics.advection import EMPTY_DENSITY
from dozerlab.learn.dynamics.models import (
    FIELD_CHANNELS,
    MOMENTUM_CHANNELS,
    MOMENTUM_DENSITY,
    DynamicsModel,
    RidgeStencil,
)


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


#: Bins along y summed at once against one layer's weights (the sums s00-s33 of
#: :func:`correct_rows`, four bins by four outputs): each weight read serves four bins, as each
#: read of the bins serves four outputs. One bin or one output at a time the reads bound the sums (BENCHMARKS.md,
#: "The ridge's stencil sums compiled" and "The ridge's sums, four outputs a read").
BLOCK = 4

#: Floats a vector of the sums holds (AVX-512's 16; AVX2's 8 divide it): each layer's run of
#: 9C weights is padded with zeros to a whole number of them, so the sums' loop has no scalar
#: remainder (11 of 315 floats took a seventh of the call; BENCHMARKS.md, "The ridge's sums,
#: three layers a pass").
LANES = 16


@njit(cache=True, fastmath={"reassoc", "contract"})
def correct_rows(
    hist_rho,
    hist_v,
    blade_v,
    base_rho,
    base_v,
    mean,
    std,
    weight,
    blank_weight,
    const,
    ctl_w,
    cond,
    box_of,
    res_std,
    rho_hi,
    v_lo,
    v_hi,
):  # pragma: no cover - compiled
    """The ridge's correction of the m advected rows (``base_rho`` (m, X, Y, Z) kg/m³,
    ``base_v`` (m, X, Y, Z, 3) m/s) from H history rows (``hist_rho``, ``hist_v``), the
    velocities relative to ``blade_v`` (H + m, 3) m/s, kept within the training range as
    :meth:`DynamicsModel.correct <dozerlab.learn.dynamics.models.DynamicsModel.correct>` does.
    Returns velocity (m, X, Y, Z, 3) and density (m, X, Y, Z).

    The model is linear, so each bin's channels are split into a blank bin's (no material, at
    rest: the same everywhere for a given blade velocity) and the fields over their spreads
    (zero in a blank bin). The blank part's sum over a neighbourhood is made once per layer
    and box from ``blank_weight`` (X, boxes, C(H + m), 4m), the stencil's weights summed over
    the 27 neighbours; the rest from ``weight`` (X, boxes, 4m, 3·S), the neighbours (i, j, k)
    and channels of a bin in the order they lie in the channel-last grid, each layer i's 9·C(H +
    m) padded with zeros to S, a multiple of :data:`LANES`; skipped
    where a bin's neighbourhood holds nothing. ``const`` (X, 4m, Y, Z) the position's and bias's
    terms, ``ctl_w`` (X, boxes, 3(H + m), 4m) the control's weights times ``cond``, the
    normalised control, ``box_of`` (Y, Z) each bin's box, ``mean`` and ``std`` (C(H + m),) the
    channels' normalisation (C channels a row: the model's ``row_channels``), ``res_std`` (4,)
    the residuals' spreads."""
    h, nx, ny, nz = hist_rho.shape
    m = base_rho.shape[0]
    ch = mean.shape[0]
    per_row = ch // (h + m)  # FIELD_CHANNELS, or MOMENTUM_CHANNELS with the momentum's three
    outs = FIELD_CHANNELS * m
    nb = ctl_w.shape[1]
    line = 3 * ch  # three bins along z and their channels
    # the fields over the channels' spreads, channel last, edges replicated (the stencil's
    # padding), and which padded bins hold anything
    py, pz = ny + 2, nz + 2
    grid = np.empty((nx + 2) * py * pz * ch, np.float32)
    filled = np.zeros((nx + 2, py, pz), np.bool_)
    inv = np.float32(1.0) / std
    for xp in range(nx + 2):
        x = min(max(xp - 1, 0), nx - 1)
        for yp in range(py):
            y = min(max(yp - 1, 0), ny - 1)
            for zp in range(pz):
                z = min(max(zp - 1, 0), nz - 1)
                at = ((xp * py + yp) * pz + zp) * ch
                full = False
                for row in range(h + m):
                    c = per_row * row
                    r = hist_rho[row, x, y, z] if row < h else base_rho[row - h, x, y, z]
                    full |= r != 0.0
                    grid[at + c] = r * inv[c]
                    for a in range(3):
                        if row < h:
                            v = hist_v[row, x, y, z, a]
                        else:
                            v = base_v[row - h, x, y, z, a]
                        full |= v != 0.0
                        grid[at + c + 1 + a] = v * inv[c + 1 + a]
                        if per_row == MOMENTUM_CHANNELS:
                            # ρ(v − v_b), zero in a blank bin as the other channels here
                            mom = r * (v - blade_v[row, a]) / np.float32(MOMENTUM_DENSITY)
                            grid[at + c + 4 + a] = mom * inv[c + 4 + a]
                filled[xp, yp, zp] = full
    blank = np.empty(ch, np.float32)
    for c in range(ch):
        row, comp = c // per_row, c % per_row
        raw = -blade_v[row, comp - 1] if 1 <= comp <= 3 else np.float32(0.0)
        blank[c] = (raw - mean[c]) * inv[c]
    fixed = np.zeros((nx, nb, outs), np.float32)
    for x in range(nx):
        for b in range(nb):
            for o in range(outs):
                acc = np.float32(0.0)
                for c in range(ch):
                    acc += blank[c] * blank_weight[x, b, c, o]
                for q in range(cond.shape[0]):
                    acc += cond[q] * ctl_w[x, b, q, o]
                fixed[x, b, o] = acc
    # each padded bin's channels beside those of the two bins above it, laid out (x, z, y, ·):
    # the 3 × 3 × 3 neighbourhood of bin (x, y, z) is then three runs of 3 lines, one per
    # layer x + i at (x + i, z, y), the order of `weight`'s rows (a copy of each bin's
    # neighbourhood took half the call's time; BENCHMARKS.md); a run is read `span` long, the
    # floats past its end meeting zero weights (zeros past the last line)
    span = weight.shape[3] // 3
    lines = np.zeros((nx + 2) * nz * py * line + span - 3 * line, np.float32)
    for xp in range(nx + 2):
        for z in range(nz):
            for yp in range(py):
                dst = ((xp * nz + z) * py + yp) * line
                src = ((xp * py + yp) * pz + z) * ch
                lines[dst : dst + line] = grid[src : src + line]
    last = lines.size - span
    sums = np.zeros((BLOCK, outs), np.float32)
    rho = np.empty((m, nx, ny, nz), np.float32)
    vel = np.empty((m, nx, ny, nz, 3), np.float32)
    for x in range(nx):
        for z in range(nz):
            y0 = 0
            while y0 < ny:
                b = box_of[y0, z]
                n = 1
                while n < BLOCK and y0 + n < ny and box_of[y0 + n, z] == b:
                    n += 1
                seen = False
                for i in range(3):
                    for j in range(n + 2):
                        for k in range(3):
                            seen |= filled[x + i, y0 + j, z + k]
                if seen:
                    # a block shorter than BLOCK reads the bins after it too (the padding, or
                    # the next block's): summed, not used
                    # four outputs at a time (outs = 4m): 16 sums in registers
                    for o in range(0, outs, 4):
                        s00 = s01 = s02 = s03 = np.float32(0.0)
                        s10 = s11 = s12 = s13 = np.float32(0.0)
                        s20 = s21 = s22 = s23 = np.float32(0.0)
                        s30 = s31 = s32 = s33 = np.float32(0.0)
                        # the three layers' runs in one loop: each sum is reduced across
                        # its vector once, not once a layer (a seventh of the call;
                        # BENCHMARKS.md, "The ridge's sums, three layers a pass"). Views:
                        # an index computed in the loop costs a check for negative values
                        # at each read, and the sums were not vectorised (7x slower)
                        at = ((x * nz + z) * py + y0) * line
                        w00 = weight[x, b, o, :span]
                        w10 = weight[x, b, o + 1, :span]
                        w20 = weight[x, b, o + 2, :span]
                        w30 = weight[x, b, o + 3, :span]
                        l00 = lines[at : at + span]
                        l10 = lines[min(at + line, last) :]
                        l20 = lines[min(at + 2 * line, last) :]
                        l30 = lines[min(at + 3 * line, last) :]
                        at = (((x + 1) * nz + z) * py + y0) * line
                        w01 = weight[x, b, o, span : 2 * span]
                        w11 = weight[x, b, o + 1, span : 2 * span]
                        w21 = weight[x, b, o + 2, span : 2 * span]
                        w31 = weight[x, b, o + 3, span : 2 * span]
                        l01 = lines[at : at + span]
                        l11 = lines[min(at + line, last) :]
                        l21 = lines[min(at + 2 * line, last) :]
                        l31 = lines[min(at + 3 * line, last) :]
                        at = (((x + 2) * nz + z) * py + y0) * line
                        w02 = weight[x, b, o, 2 * span :]
                        w12 = weight[x, b, o + 1, 2 * span :]
                        w22 = weight[x, b, o + 2, 2 * span :]
                        w32 = weight[x, b, o + 3, 2 * span :]
                        l02 = lines[at : at + span]
                        l12 = lines[min(at + line, last) :]
                        l22 = lines[min(at + 2 * line, last) :]
                        l32 = lines[min(at + 3 * line, last) :]
                        for t in range(span):
                            a0, a1, a2, a3 = l00[t], l10[t], l20[t], l30[t]
                            c0, c1, c2, c3 = w00[t], w10[t], w20[t], w30[t]
                            s00 += a0 * c0
                            s01 += a0 * c1
                            s02 += a0 * c2
                            s03 += a0 * c3
                            s10 += a1 * c0
                            s11 += a1 * c1
                            s12 += a1 * c2
                            s13 += a1 * c3
                            s20 += a2 * c0
                            s21 += a2 * c1
                            s22 += a2 * c2
                            s23 += a2 * c3
                            s30 += a3 * c0
                            s31 += a3 * c1
                            s32 += a3 * c2
                            s33 += a3 * c3
                            a0, a1, a2, a3 = l01[t], l11[t], l21[t], l31[t]
                            c0, c1, c2, c3 = w01[t], w11[t], w21[t], w31[t]
                            s00 += a0 * c0
                            s01 += a0 * c1
                            s02 += a0 * c2
                            s03 += a0 * c3
                            s10 += a1 * c0
                            s11 += a1 * c1
                            s12 += a1 * c2
                            s13 += a1 * c3
                            s20 += a2 * c0
                            s21 += a2 * c1
                            s22 += a2 * c2
                            s23 += a2 * c3
                            s30 += a3 * c0
                            s31 += a3 * c1
                            s32 += a3 * c2
                            s33 += a3 * c3
                            a0, a1, a2, a3 = l02[t], l12[t], l22[t], l32[t]
                            c0, c1, c2, c3 = w02[t], w12[t], w22[t], w32[t]
                            s00 += a0 * c0
                            s01 += a0 * c1
                            s02 += a0 * c2
                            s03 += a0 * c3
                            s10 += a1 * c0
                            s11 += a1 * c1
                            s12 += a1 * c2
                            s13 += a1 * c3
                            s20 += a2 * c0
                            s21 += a2 * c1
                            s22 += a2 * c2
                            s23 += a2 * c3
                            s30 += a3 * c0
                            s31 += a3 * c1
                            s32 += a3 * c2
                            s33 += a3 * c3
                        sums[0, o : o + 4] = (s00, s01, s02, s03)
                        sums[1, o : o + 4] = (s10, s11, s12, s13)
                        sums[2, o : o + 4] = (s20, s21, s22, s23)
                        sums[3, o : o + 4] = (s30, s31, s32, s33)
                else:
                    sums[:] = 0.0
                for q in range(n):
                    y = y0 + q
                    for j in range(m):
                        f = FIELD_CHANNELS * j
                        r = (sums[q, f] + fixed[x, b, f] + const[x, f, y, z]) * res_std[0]
                        rho[j, x, y, z] = min(
                            max(base_rho[j, x, y, z] + r, np.float32(0.0)), rho_hi
                        )
                        for a in range(3):
                            o = f + 1 + a
                            r = (sums[q, o] + fixed[x, b, o] + const[x, o, y, z]) * res_std[1 + a]
                            vel[j, x, y, z, a] = max(
                                min(base_v[j, x, y, z, a] + r, v_hi[a]), v_lo[a]
                            )
                y0 += n
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
        ch = model.row_channels * (self.history + self.horizon)
        d, outs = 27 * ch, FIELD_CHANNELS * self.horizon
        boxes = list(net.boxes)
        with torch.no_grad():
            w, bias = net.weight.detach().float().cpu(), net.bias.detach().float().cpu()
            pos = model.coords.cpu().permute(1, 2, 3, 0)
            # weight row c·27 + n (n = 9i + 3j + k) → (layer, box, output, n·C + c)
            stencil = w[:, :, :d].reshape(nx, len(boxes), ch, 27, outs)
            run = 9 * ch  # a layer's neighbours and channels
            span = -(-run // LANES) * LANES
            weight = torch.zeros(nx, len(boxes), outs, 3, span)
            weight[..., :run] = stencil.permute(0, 1, 4, 3, 2).reshape(nx, len(boxes), outs, 3, run)
            weight = weight.reshape(nx, len(boxes), outs, 3 * span)
            const = torch.zeros(nx, outs, ny, nz)
            box_of = np.zeros((ny, nz), np.int64)
            for k, (y0, y1, z0, z1) in enumerate(boxes):
                lin = torch.einsum("xyzp,xpo->xoyz", pos[:, y0:y1, z0:z1], w[:, k, d : d + 3])
                const[:, :, y0:y1, z0:z1] = lin + bias[:, k, :, None, None]
                box_of[y0:y1, z0:z1] = k
        self.weight, self.blank_weight = _numpy(weight), _numpy(stencil.sum(dim=3))
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
        cond = (vb.reshape(-1) - self.cond_mean) / self.cond_std
        return correct_rows(
            rho,
            v,
            vb,
            base_rho,
            base_v,
            self.chan_mean,
            self.chan_std,
            self.weight,
            self.blank_weight,
            self.const,
            self.ctl_w,
            cond,
            self.box_of,
            self.res_std,
            self.rho_hi,
            self.v_lo,
            self.v_hi,
        )
