"""Projected Gauss-Seidel (optionally with NNCG momentum) on the SPOOK rows, swept in parallel.

Multipliers ``lam`` (Nc, 7) are impulses (N·s): the normal one, the friction impulse as a world
vector in the tangent plane (3) and the rolling-resistance angular impulse (3). Per contact the
normal row is solved first, then friction projected onto the disc μ·λ_n, then rolling
resistance projected onto the disc R*·μ_r·λ_n; each update is applied to the velocities at once.
With spinning resistance (``spin`` = μ_s > 0) the angular impulse also has a component along the
normal, the third rolling row, which resists the relative spin about the normal and is clipped to
±R*·μ_s·λ_n; without it that component is zero and spin about the normal is free.

Parallel sweep: group s < S holds the contacts inside slab s, group S + s those joining slabs
s and s + 1. A task sweeps slab s and then its boundary with s + 1, so it touches only those two
slabs; the tasks of even slabs run in parallel, then those of odd slabs. No two concurrent tasks
share a particle, so no locks are needed, and the result does not depend on the thread count.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from dozerlab.ndem.contacts import KN, KR, KT, MU, MUR, N0, RI, RJ, SIG, VB, WB, B

# A Hertz row is taken again when its pair sinks past this multiple of the overlap its
# compliance was taken at (a factor, not any excess: the round costs a solve) and past this
# fraction of the smaller radius (grains coming to rest on each other sink by less).
SINK = 2.0
SINK_FLOOR = 0.01


@njit(cache=True, fastmath=True, error_model="numpy", inline="always")
def _clip(t0, t1, t2, lim):
    """The vector t scaled onto the disc |t| <= ``lim`` when it lies outside (the friction and
    the rolling rows share this step; inlined, so it costs no call)."""
    mag2 = t0 * t0 + t1 * t1 + t2 * t2
    if mag2 > lim * lim:
        sc = lim / np.sqrt(mag2)
        return t0 * sc, t1 * sc, t2 * sc
    return t0, t1, t2


@njit(cache=True, fastmath=True, error_model="numpy", inline="always")
def _solve(k, ci, cj, cd, lam, v, w, invm, invI, omega, spin):
    """One PGS update of contact k, its steps scaled by ``omega`` (over-relaxation when > 1),
    with the spinning row when ``spin`` (μ_s) > 0; returns the squared normal-row residual and
    the squared velocity change the update made at the contact point over ω (m²/s²: translation,
    friction turn and rolling, as surface speeds).

    The rows are solved in order (normal, friction, rolling), each seeing the ones before, but
    written so that little waits on the row before: the normal update is along n, so the
    friction row's tangential slip is taken from the velocities before it, and the friction
    update turns w by a tangential n × d, so the rolling row adds that to the tangential
    relative angular velocity taken before it. The multipliers stay in the tangent plane (the
    warm start projects them onto it; but for the rolling one's spinning component), so no row
    projects them again. Same arithmetic up to
    round-off as applying each update to the velocities in turn; the sweep's time is the
    latency of this chain (BENCHMARKS.md "NDEM sweep kernel").
    """
    i = ci[k]
    j = cj[k]
    c = cd[k]
    n0, n1, n2 = c[N0], c[N0 + 1], c[N0 + 2]
    imi = invm[i]
    iii = invI[i]
    if j >= 0:
        imj = invm[j]
        iij = invI[j]
        vj0, vj1, vj2 = v[j, 0], v[j, 1], v[j, 2]
        wj0, wj1, wj2 = w[j, 0], w[j, 1], w[j, 2]
    else:
        imj = 0.0
        iij = 0.0
        vj0, vj1, vj2 = c[VB], c[VB + 1], c[VB + 2]
        wj0, wj1, wj2 = c[WB], c[WB + 1], c[WB + 2]
    vi0, vi1, vi2 = v[i, 0], v[i, 1], v[i, 2]
    wi0, wi1, wi2 = w[i, 0], w[i, 1], w[i, 2]

    # Normal row.
    g0, g1, g2 = vi0 - vj0, vi1 - vj1, vi2 - vj2
    ln = lam[k, 0]
    un = n0 * g0 + n1 * g1 + n2 * g2
    ln_new = max(0.0, ln + omega * (c[B] - un - c[SIG] * ln) * c[KN])
    dn = ln_new - ln
    lam[k, 0] = ln_new
    res = dn / (omega * c[KN])
    l1, l2, l3 = lam[k, 1], lam[k, 2], lam[k, 3]
    l4, l5, l6 = lam[k, 4], lam[k, 5], lam[k, 6]
    if ln_new == 0.0 and l1 == l2 == l3 == l4 == l5 == l6 == 0.0:
        # Separating or speculative and unloaded: the friction and rolling discs are points.
        if dn != 0.0:
            v[i, 0], v[i, 1], v[i, 2] = (
                vi0 + dn * imi * n0,
                vi1 + dn * imi * n1,
                vi2 + dn * imi * n2,
            )
            if j >= 0:
                v[j, 0], v[j, 1], v[j, 2] = (
                    vj0 - dn * imj * n0,
                    vj1 - dn * imj * n1,
                    vj2 - dn * imj * n2,
                )
        du = dn * (imi + imj) / omega
        return res * res, du * du

    # Friction: the trial impulse from the contact points' tangential relative velocity.
    ri = c[RI]
    rj = c[RJ]
    s0 = ri * wi0 + rj * wj0
    s1 = ri * wi1 + rj * wj1
    s2 = ri * wi2 + rj * wj2
    u0 = g0 - (s1 * n2 - s2 * n1)
    u1 = g1 - (s2 * n0 - s0 * n2)
    u2 = g2 - (s0 * n1 - s1 * n0)
    ut = u0 * n0 + u1 * n1 + u2 * n2
    kt = omega * c[KT]
    t0, t1, t2 = _clip(
        l1 - kt * (u0 - ut * n0), l2 - kt * (u1 - ut * n1), l3 - kt * (u2 - ut * n2), c[MU] * ln_new
    )
    d0, d1, d2 = t0 - l1, t1 - l2, t2 - l3
    lam[k, 1], lam[k, 2], lam[k, 3] = t0, t1, t2
    p0, p1, p2 = dn * n0 + d0, dn * n1 + d1, dn * n2 + d2
    x0 = n1 * d2 - n2 * d1  # n × d: the friction update turns w_i by -I_i⁻¹ r_i x
    x1 = n2 * d0 - n0 * d2
    x2 = n0 * d1 - n1 * d0
    qi = iii * ri
    qj = iij * rj

    # Rolling resistance on the tangential relative angular velocity after the friction update.
    a0 = wi0 - wj0
    a1 = wi1 - wj1
    a2 = wi2 - wj2
    q = qj - qi
    kr = omega * c[KR]
    if spin > 0.0:
        # and the spinning row: the whole relative angular velocity (the spheres' inverse
        # inertias are isotropic, so the three rows share KR), the tangential part clipped onto
        # the rolling disc, the normal part onto ±R*·μ_s·λ_n (R* from the lever arms)
        b0 = l4 - kr * (a0 + q * x0)
        b1 = l5 - kr * (a1 + q * x1)
        b2 = l6 - kr * (a2 + q * x2)
        bn = b0 * n0 + b1 * n1 + b2 * n2
        r0, r1, r2 = _clip(b0 - bn * n0, b1 - bn * n1, b2 - bn * n2, c[MUR] * ln_new)
        lim = spin * ln_new * (ri * rj / (ri + rj) if rj > 0.0 else ri)
        bn = min(max(bn, -lim), lim)
        r0, r1, r2 = r0 + bn * n0, r1 + bn * n1, r2 + bn * n2
    else:
        an = a0 * n0 + a1 * n1 + a2 * n2
        r0, r1, r2 = _clip(
            l4 - kr * (a0 - an * n0 + q * x0),
            l5 - kr * (a1 - an * n1 + q * x1),
            l6 - kr * (a2 - an * n2 + q * x2),
            c[MUR] * ln_new,
        )
    e0, e1, e2 = r0 - l4, r1 - l5, r2 - l6
    lam[k, 4], lam[k, 5], lam[k, 6] = r0, r1, r2

    v[i, 0], v[i, 1], v[i, 2] = vi0 + imi * p0, vi1 + imi * p1, vi2 + imi * p2
    w[i, 0] = wi0 - qi * x0 + iii * e0
    w[i, 1] = wi1 - qi * x1 + iii * e1
    w[i, 2] = wi2 - qi * x2 + iii * e2
    if j >= 0:
        v[j, 0], v[j, 1], v[j, 2] = vj0 - imj * p0, vj1 - imj * p1, vj2 - imj * p2
        w[j, 0] = wj0 - qj * x0 - iij * e0
        w[j, 1] = wj1 - qj * x1 - iij * e1
        w[j, 2] = wj2 - qj * x2 - iij * e2
    # the velocity change of the update at the contact point: translation, the turn of the
    # friction update and the rolling update, each as a surface speed (friction and rolling
    # count, so a stop on it leaves no grain creeping on an unconverged friction row), before
    # the relaxation (as the residual), so ω does not delay the stop
    sm = imi + imj
    sq = qi * ri + qj * rj
    sr = iii * ri + iij * rj
    du2 = (
        sm * sm * (p0 * p0 + p1 * p1 + p2 * p2)
        + sq * sq * (x0 * x0 + x1 * x1 + x2 * x2)
        + sr * sr * (e0 * e0 + e1 * e1 + e2 * e2)
    )
    return res * res, du2 / (omega * omega)


@njit(cache=True, inline="always")
def _apply(k, ci, cj, cd, lam, v, w, invm, invI):
    """Apply contact k's multipliers (a warm start) to the velocities."""
    i = ci[k]
    j = cj[k]
    for a in range(3):
        p = lam[k, 0] * cd[k, N0 + a] + lam[k, 1 + a]
        v[i, a] += invm[i] * p
        if j >= 0:
            v[j, a] -= invm[j] * p
    n = cd[k, N0 : N0 + 3]
    x = np.cross(n, lam[k, 1:4])
    for a in range(3):
        w[i, a] += invI[i] * (lam[k, 4 + a] - cd[k, RI] * x[a])
        if j >= 0:
            w[j, a] -= invI[j] * (lam[k, 4 + a] + cd[k, RJ] * x[a])


@njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def solve(
    ci,
    cj,
    cd,
    lam,
    v,
    w,
    invm,
    invI,
    start,
    n_slabs,
    iterations,
    warm,
    method,
    tolerance,
    omega,
    spin=0.0,
    largest=0.0,
):
    """Sweep the contacts until a sweep changed the velocities at the contact points by less
    than ``tolerance`` (m/s, RMS over the contacts of every row's change), or by at most
    ``largest`` at every contact (m/s, each contact's change over its rows, as for the RMS), or
    ``iterations`` sweeps ran (a stop at 0 is off).

    Each update is scaled by ``omega`` (projected SOR when > 1). ``spin`` is the spinning
    resistance μ_s (0: spin about the normal is free, the rolling impulse stays tangential; the
    warm start must then have dropped its normal component). ``method`` is an index into
    :data:`dozerlab.ndem.params.METHODS`: 0 PGS; 1 NNCG
    (Silcowitz, Niebe & Erleben 2010), which after each sweep adds β·p to the multipliers, p
    the previous search direction and β = |Δλ_k|² / |Δλ_{k-1}|² (Fletcher–Reeves on the sweep's
    step Δλ), restarting (β = 0) when β > 1; the last sweep adds nothing, so the multipliers
    returned are projected ones. The velocities follow λ through u = M⁻¹Jᵀp per sphere,
    updated from each sweep's velocity change, so the momentum costs no pass over the rows.
    Returns the RMS normal-row update of the last sweep (m/s) and the sweeps run. With
    ``warm`` the incoming ``lam`` are first applied to ``v``/``w``; otherwise ``lam`` must be
    zero. Sums are taken per slab task and then in slab order, so the result does not depend
    on the thread count. ``start`` (2S + 2,) holds the group offsets of
    :func:`dozerlab.ndem.contacts.assemble`; the frozen group 2S is applied but not swept.
    """
    n = v.shape[0]
    if warm:
        for k in range(ci.shape[0]):
            _apply(k, ci, cj, cd, lam, v, w, invm, invI)
    # the contacts swept: the groups before 2S (group 2S, the frozen ones, is left as it is)
    nc = start[2 * n_slabs]
    nncg = method == 1
    mc = nc if nncg else 0
    ms = n if nncg else 0
    prev = np.empty((mc, 7))  # λ before the sweep
    p = np.zeros((mc, 7))  # search direction in λ
    vw_prev = np.empty((ms, 6))  # v, w before the sweep
    u = np.zeros((ms, 6))  # M⁻¹Jᵀp: the search direction in velocities
    res_part = np.zeros(n_slabs)
    step_part = np.zeros(n_slabs)
    du_part = np.zeros(n_slabs)
    top_part = np.zeros(n_slabs)
    res = 0.0
    step_norm_old = 0.0
    threshold = tolerance * tolerance * max(nc, 1)
    done = 0
    while done < iterations:
        if nncg:
            for i in prange(n):
                for a in range(3):
                    vw_prev[i, a] = v[i, a]
                    vw_prev[i, 3 + a] = w[i, a]
        for phase in range(2):
            for m in prange((n_slabs - phase + 1) // 2):
                s = 2 * np.int64(m) + phase  # prange indices may be unsigned
                r = 0.0
                d2 = 0.0
                du = 0.0
                top = 0.0
                for g in (s, n_slabs + s):
                    if g == 2 * n_slabs - 1:
                        continue  # the last slab has no boundary group
                    for k in range(start[g], start[g + 1]):
                        if nncg:
                            for a in range(7):
                                prev[k, a] = lam[k, a]
                        rk, uk = _solve(k, ci, cj, cd, lam, v, w, invm, invI, omega, spin)
                        r += rk
                        du += uk
                        top = max(top, uk)
                        if nncg:
                            for a in range(7):
                                d = lam[k, a] - prev[k, a]
                                d2 += d * d
                res_part[s] = r
                step_part[s] = d2
                du_part[s] = du
                top_part[s] = top
        done += 1
        res = 0.0
        step_norm = 0.0
        change = 0.0
        worst = 0.0
        for t in range(n_slabs):
            res += res_part[t]
            step_norm += step_part[t]
            change += du_part[t]
            worst = max(worst, top_part[t])
        if (tolerance > 0.0 and change <= threshold) or (
            largest > 0.0 and worst <= largest * largest
        ):
            break
        if not nncg or done == iterations:
            continue
        beta = 0.0
        if step_norm_old > 0.0 and step_norm <= step_norm_old:
            beta = step_norm / step_norm_old
        step_norm_old = step_norm
        for k in prange(nc):
            for a in range(7):
                q = beta * p[k, a]
                p[k, a] = q + lam[k, a] - prev[k, a]
                lam[k, a] += q
        for i in prange(n):
            for a in range(3):
                q = beta * u[i, a]
                u[i, a] = q + v[i, a] - vw_prev[i, a]
                v[i, a] += q
                q = beta * u[i, 3 + a]
                u[i, 3 + a] = q + w[i, a] - vw_prev[i, 3 + a]
                w[i, a] += q
    return np.sqrt(res / max(nc, 1)), done


@njit(parallel=True, cache=True)
def integrate(x, v, w, h):
    """Advance positions by h·v (symplectic Euler); returns True when any value is not finite."""
    bad = np.zeros(x.shape[0], dtype=np.bool_)
    for i in prange(x.shape[0]):
        for a in range(3):
            x[i, a] += h * v[i, a]
            if not (np.isfinite(x[i, a]) and np.isfinite(v[i, a]) and np.isfinite(w[i, a])):
                bad[i] = True
    return bad.any()


@njit(parallel=True, cache=True)
def all_finite(x, v, w):
    """True when every position, velocity and angular velocity is finite."""
    bad = np.zeros(x.shape[0], dtype=np.bool_)
    for i in prange(x.shape[0]):
        for a in range(3):
            if not (np.isfinite(x[i, a]) and np.isfinite(v[i, a]) and np.isfinite(w[i, a])):
                bad[i] = True
    return not bad.any()


@njit(cache=True, inline="always")
def _end_overlap(k, ci, cj, cd, gap, v, r, h):
    """Row ``k``'s pair: the overlap g − h·uₙ (m) it reaches by the end of the step with the
    velocities ``v``, and its smaller radius (m; the sphere's own against a body)."""
    i = ci[k]
    j = cj[k]
    un = 0.0
    for a in range(3):
        vj = v[j, a] if j >= 0 else cd[k, VB + a]
        un += cd[k, N0 + a] * (v[i, a] - vj)
    return gap[k] - h * un, (min(r[i], r[j]) if j >= 0 else r[i])


@njit(cache=True)
def deepest_end(ci, cj, cd, gap, v, r, h, swept, compliant=True):
    """The largest overlap over the smaller radius that a compliant Hertz row's pair reaches by
    the end of the step, g − h·uₙ with the solved velocities (0 if none), over the first
    ``swept`` rows: what :func:`stiffen` reads, to tell a step that needs its rounds; with
    ``compliant`` False, over every row (stiff contacts too)."""
    worst = 0.0
    for k in range(swept):
        if compliant and (cd[k, SIG] <= 0.0 or cd[k, KN] <= 0.0):
            continue
        g_end, rmin = _end_overlap(k, ci, cj, cd, gap, v, r, h)
        worst = max(worst, g_end / rmin)
    return worst


@njit(parallel=True, cache=True)
def stiffen(ci, cj, cd, gap, v, r, estar, h, upsilon, swept, awake, soft):
    """Re-linearise, in place, the Hertz rows whose pair reaches by the end of the step an
    overlap over :data:`SINK` times the one their compliance was taken at and over
    :data:`SINK_FLOOR` of the smaller radius; returns how many.

    A compliant row's compliance 4 / (5 k_n √g) is evaluated at assembly from the pair's
    approach at the start of the step. A pair touching at rest that a load reaches through
    the contact network within the step was taken nearly unloaded (g ≈ 0: a near-infinite
    compliance) and sinks by a whole step's travel; evaluated again at the overlap
    g − h·uₙ the current velocities reach, the row carries the load. Only rows with Σ > 0
    (compliant, not speculative) among the first ``swept`` (the frozen group, after them, is
    never swept) change; Σ only decreases (stiffer). ``gap`` (Nc,) m, ``v`` (N, 3) m/s after
    the solve, ``r`` (N,) m, ``estar`` Pa, ``h`` s, ``upsilon``, ``awake`` (N,) and ``soft`` as
    in the assembly (a row with a sleeper keeps its ``soft`` times the compliance).
    """
    changed = np.zeros(swept, dtype=np.int64)
    for k in prange(swept):
        sig = cd[k, SIG]
        if sig <= 0.0 or cd[k, KN] <= 0.0:
            continue
        g_end, rmin = _end_overlap(k, ci, cj, cd, gap, v, r, h)
        if g_end <= SINK_FLOOR * rmin:
            continue
        i = ci[k]
        j = cj[k]
        rstar = r[i] * r[j] / (r[i] + r[j]) if j >= 0 else r[i]
        kn = 4.0 / 3.0 * estar * np.sqrt(rstar)
        scale = soft if j >= 0 and not (awake[i] and awake[j]) else 1.0
        # the overlap Σ was taken at: Σ = scale · 16 Υ / (5 k_n h² √g)
        root = scale * 16.0 * upsilon / (5.0 * kn * h * h * sig)
        if g_end > SINK * root * root:
            new = scale * 16.0 * upsilon / (5.0 * kn * h * h * np.sqrt(g_end))
            sn = 1.0 / cd[k, KN] - sig
            cd[k, SIG] = new
            cd[k, KN] = 1.0 / (sn + new)
            changed[k] = 1
    return changed.sum()
