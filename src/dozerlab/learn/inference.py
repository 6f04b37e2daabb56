"""The linear force model's forward over many rows at once, as the reduced loop calls it.

:class:`LinearForceRows` computes what :meth:`ForceModel.forward
<dozerlab.learn.models.ForceModel.forward>` computes for a ``linear`` model (its
:class:`~dozerlab.learn.models.LinearHead`), to float32 round-off, without building the
channels bin by bin: the head reads each channel only through its sum over y and its first
moment Σ y·c, and every channel is a product of the velocity, the density and the blade
velocity, so the sums of Σ_y v, Σ_y ρ, Σ_y ρv and their moments over each (x, z) column
(:func:`column_sums`, one pass over the bins) give every channel's sum, normalised after the
sum (Σ_y (c − m)/s = (Σ_y c − N_y m)/s), and each feature meets the head's weights as it is
made. On the 303 rows of the default sweep's step 1.0 / 0.12 the loop's force model (history
1, contact inputs) takes 6.1 ms against 18–24 ms through the module in batches of 16, the
NDEM-trained one (history 3) 14–23 ms against 56–78 ms (BENCHMARKS.md, "The loop's force rows
from column sums").
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from dozerlab.learn.models import CHANNELS_PER_STEP, ForceModel, LinearHead

#: Per (row, x, z) column: Σ_y of v (3), ρ, ρv (3), then Σ_y y· of the same seven.
SUMS = 14
#: The channels of a step's change (Δρ, Δ(ρv)) among a step's own channels.
CHANGED = np.array([3, 7, 8, 9], np.int64)


@njit(cache=True)
def column_sums(vel, rho, x0, y0, y1, z1, ycoord):  # pragma: no cover - compiled
    """(T, X − x0, z1, 14) float64: for each row of ``vel`` (T, X, Y, Z, 3) m/s and ``rho``
    (T, X, Y, Z) kg/m³ and each (x, z) column of the blade part [x0:, y0:y1, :z1], the sums over
    y of v, ρ, ρv and their first moments with the weights ``ycoord`` (y1 − y0,)."""
    t_n, nx = rho.shape[0], rho.shape[1]
    out = np.empty((t_n, nx - x0, z1, SUMS))
    acc = np.empty(SUMS)
    for t in range(t_n):
        for x in range(x0, nx):
            for z in range(z1):
                acc[:] = 0.0
                for y in range(y0, y1):
                    w = ycoord[y - y0]
                    r = np.float64(rho[t, x, y, z])
                    for a in range(3):
                        v = np.float64(vel[t, x, y, z, a])
                        acc[a] += v
                        acc[4 + a] += r * v
                        acc[7 + a] += w * v
                        acc[11 + a] += w * r * v
                    acc[3] += r
                    acc[10] += w * r
                out[t, x - x0, z] = acc
    return out


@njit(cache=True)
def _channel(s, vb, k, ny, ysum):  # pragma: no cover - compiled
    """Sum over y and first moment of a step's own channel ``k`` (0–9: v − v_b, ρ, ρ(v − v_b),
    ρv) from a column's sums ``s`` (14,) and the blade velocity ``vb`` (3,)."""
    if k < 3:
        return s[k] - ny * vb[k], s[7 + k] - ysum * vb[k]
    if k == 3:
        return s[3], s[10]
    if k < 7:
        a = k - 4
        return s[4 + a] - vb[a] * s[3], s[11 + a] - vb[a] * s[10]
    return s[k - 3], s[k + 4]


@njit(cache=True)
def field_terms(
    sums, vb, history, ny, ysum, mean, std, odd, changed, w_even, w_odd
):  # pragma: no cover
    """The head's field features times its weights, summed: (T, E) and (T, O) for the even and
    odd weights ``w_even`` (C·X·Z, E) and ``w_odd`` (C·X·Z, O) of the features in the head's
    (channel, x, z) order. A channel's even feature is its normalised y-sum where it is even
    under the mirror (its moment where odd), its odd feature the other. ``sums`` (T, X, Z, 14)
    per row (:func:`column_sums`), ``vb`` (T, 3) m/s; a row's history steps are the rows before
    it, the first repeated (as the pyfunc's). Accumulated feature by feature: the designs of
    the 303 rows of a run with three steps of history (20 MB) cost more to write than this."""
    t_n, nx, nz = sums.shape[0], sums.shape[1], sums.shape[2]
    n_ch = mean.shape[0]
    cols = nx * nz
    out_e = np.zeros((t_n, w_even.shape[1]))
    out_o = np.zeros((t_n, w_odd.shape[1]))
    for t in range(t_n):
        for c in range(n_ch):
            if c < CHANNELS_PER_STEP * history:
                h, k = divmod(c, CHANNELS_PER_STEP)
                r = max(t - history + 1 + h, 0)
                r0 = -1
            else:
                h, j = divmod(c - CHANNELS_PER_STEP * history, changed.shape[0])
                k = changed[j]
                r0 = max(t - history + 1 + h, 0)
                r = max(t - history + 2 + h, 0)
            m, sd = mean[c], std[c]
            for x in range(nx):
                for z in range(nz):
                    tot, mom = _channel(sums[r, x, z], vb[r], k, ny, ysum)
                    if r0 >= 0:
                        t0, m0 = _channel(sums[r0, x, z], vb[r0], k, ny, ysum)
                        tot, mom = tot - t0, mom - m0
                    tot = (tot - ny * m) / sd
                    mom = (mom - ysum * m) / sd
                    e, o = (mom, tot) if odd[c] else (tot, mom)
                    i = c * cols + x * nz + z
                    for q in range(out_e.shape[1]):
                        out_e[t, q] += e * w_even[i, q]
                    for q in range(out_o.shape[1]):
                        out_o[t, q] += o * w_odd[i, q]
    return out_e, out_o


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().to("cpu", torch.float64).numpy()


class LinearForceRows:
    """A ``linear`` :class:`ForceModel`'s predictions for every row of a run at once.

    ``LinearForceRows(model)(velocity (T, X, Y, Z, 3) m/s, density (T, X, Y, Z) kg/m³,
    blade_velocity (T, 3) m/s)`` → (T, 6) float64 force (N) and torque (N·m), row t from the
    ``history`` rows up to it, as the model's pyfunc gives them (float32 round-off apart).
    """

    def __init__(self, model: ForceModel) -> None:
        if model.kind != "linear":
            raise ValueError(f"LinearForceRows needs a linear force model, got {model.kind!r}")
        head = model.backbone
        assert isinstance(head, LinearHead)
        self.grid = tuple(model.grid)
        self.history = int(model.history)
        self.contact = bool(model.contact)
        self.part = tuple(int(n) for n in model.blade_part)
        self.ycoord = _numpy(head.y_coord).ravel()
        self.ny = float(self.ycoord.size)
        self.ysum = float(self.ycoord.sum())
        self.chan_mean, self.chan_std = _numpy(model.chan_mean), _numpy(model.chan_std)
        self.cond_mean, self.cond_std = _numpy(model.cond_mean), _numpy(model.cond_std)
        self.y_mean, self.y_std = _numpy(model.y_mean), _numpy(model.y_std)
        self.chan_odd = head.chan_odd.cpu().numpy()
        self.cond_odd = head.cond_odd.cpu().numpy()
        self.target_odd = head.target_odd.cpu().numpy()
        self.w_even, self.b_even = _numpy(head.even.weight).T.copy(), _numpy(head.even.bias)
        self.w_odd, self.b_odd = _numpy(head.odd.weight).T.copy(), _numpy(head.odd.bias)

    def __call__(
        self, velocity: np.ndarray, density: np.ndarray, blade_velocity: np.ndarray
    ) -> np.ndarray:
        t_n = density.shape[0]
        expected = {
            "velocity": (velocity.shape, (t_n, *self.grid, 3)),
            "density": (density.shape, (t_n, *self.grid)),
            "blade_velocity": (blade_velocity.shape, (t_n, 3)),
        }
        for name, (got, want) in expected.items():
            if tuple(got) != want:
                raise ValueError(f"{name} must have shape {want}, got {tuple(got)}")
        if t_n == 0:
            return np.zeros((0, 6))
        x0, y0, y1, z1 = self.part
        vb = np.ascontiguousarray(blade_velocity, dtype=np.float64)
        sums = column_sums(
            np.ascontiguousarray(velocity),
            np.ascontiguousarray(density),
            x0,
            y0,
            y1,
            z1,
            self.ycoord,
        )
        # the even weights of the field features: plain, and with contact inputs also those of
        # the gate times them (the head's even design is [plain, gate · plain, gate])
        d = self.w_odd.shape[0] - int(self.cond_odd.sum())
        plain_w = self.w_even[:d]
        if self.contact:
            plain = self.w_even.shape[0] // 2
            plain_w = np.concatenate([plain_w, self.w_even[plain : plain + d]], axis=1)
        even_f, odd_f = field_terms(
            sums,
            vb,
            self.history,
            self.ny,
            self.ysum,
            self.chan_mean,
            self.chan_std,
            self.chan_odd,
            CHANGED,
            plain_w,
            self.w_odd[:d],
        )
        # the conditioning: the steps' blade velocities oldest first, then the pushing gate
        steps = np.clip(np.arange(t_n)[:, None] + np.arange(1 - self.history, 1), 0, None)
        cond = vb[steps].reshape(t_n, -1)
        if self.contact:
            speed = np.linalg.norm(vb, axis=1)
            share = np.where(
                speed > 0, np.clip(vb[:, 0], 0.0, None) / np.maximum(speed, 1e-12), 0.0
            )
            face = np.asarray(density[:, x0, y0:y1, :z1], dtype=np.float64).mean(axis=(1, 2))
            cond = np.concatenate([cond, (share * face)[:, None]], axis=1)
        c = (cond - self.cond_mean) / self.cond_std
        odd = odd_f + c[:, self.cond_odd] @ self.w_odd[d:] + self.b_odd
        if self.contact:
            even_c = c[:, :-1][:, ~self.cond_odd[:-1]]
            gate = c[:, -1:]
            even = (
                even_f[:, :3]
                + even_c @ self.w_even[d:plain]
                + gate * (even_f[:, 3:] + even_c @ self.w_even[plain + d : 2 * plain])
                + gate * self.w_even[-1]
            )
        else:
            even = even_f + c[:, ~self.cond_odd] @ self.w_even[d:]
        out = np.empty((t_n, 6))
        out[:, ~self.target_odd] = even + self.b_even
        out[:, self.target_odd] = odd
        out = out * self.y_std + self.y_mean
        if self.contact:
            # one-sided contact, as the module: the grains push the blade, they cannot pull it
            out[:, 0] = np.minimum(out[:, 0], 0.0)
        return out
