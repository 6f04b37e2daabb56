"""Narrow phase against planes and boxes, and assembly of the SPOOK contact rows.

A contact joins a sphere slot ``i`` and either a sphere slot ``j >= 0`` or a body
``j = -(b + 1)``. Its normal points from j to i (a positive multiplier pushes i along it). The
rows' constants live in one (Nc, NCOL) float64 table, laid out per contact for cache locality.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

from dozerlab.ndem.broadphase import hit_buffers

PLANE = 0
BOX = 1

# Columns of the contact table.
N0 = 0  # normal (3)
RI = 3  # lever arm of i: centre → contact point (m)
RJ = 4  # lever arm of j (0 for bodies)
SIG = 5  # normal-row compliance Σ (m/(N·s))
B = 6  # normal-row right-hand side (m/s)
MU = 7  # Coulomb friction μ
MUR = 8  # rolling limit factor R*·μ_r (m)
KN = 9  # 1 / (S_n + Σ)
KT = 10  # 1 / S_t
KR = 11  # 1 / S_r
VB = 12  # body velocity at the contact point (3)
WB = 15  # body angular velocity (3)
NCOL = 18


@njit(cache=True, inline="always")
def _body_test(x, r, margin, kind, c, rot, ext, nrm):
    """Overlap (m) of a sphere (x, r) with one body and the normal out of the body (3 floats)."""
    dx0, dx1, dx2 = x[0] - c[0], x[1] - c[1], x[2] - c[2]
    if kind == PLANE:
        return r - (dx0 * nrm[0] + dx1 * nrm[1] + dx2 * nrm[2]), nrm[0], nrm[1], nrm[2]
    reach = r + margin + np.sqrt(ext[0] * ext[0] + ext[1] * ext[1] + ext[2] * ext[2])
    if dx0 * dx0 + dx1 * dx1 + dx2 * dx2 > reach * reach:
        return -np.inf, 0.0, 0.0, 1.0
    # Local coordinates (rot's columns are the box axes), clamped onto the box.
    p0 = dx0 * rot[0, 0] + dx1 * rot[1, 0] + dx2 * rot[2, 0]
    p1 = dx0 * rot[0, 1] + dx1 * rot[1, 1] + dx2 * rot[2, 1]
    p2 = dx0 * rot[0, 2] + dx1 * rot[1, 2] + dx2 * rot[2, 2]
    d0 = p0 - min(max(p0, -ext[0]), ext[0])
    d1 = p1 - min(max(p1, -ext[1]), ext[1])
    d2 = p2 - min(max(p2, -ext[2]), ext[2])
    dist = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if dist > 0.0:
        l0, l1, l2 = d0 / dist, d1 / dist, d2 / dist
        g = r - dist
    else:  # centre inside: leave through the nearest face
        e0, e1, e2 = ext[0] - abs(p0), ext[1] - abs(p1), ext[2] - abs(p2)
        l0, l1, l2 = 0.0, 0.0, 0.0
        if e0 <= e1 and e0 <= e2:
            l0, g = (1.0 if p0 >= 0.0 else -1.0), r + e0
        elif e1 <= e2:
            l1, g = (1.0 if p1 >= 0.0 else -1.0), r + e1
        else:
            l2, g = (1.0 if p2 >= 0.0 else -1.0), r + e2
    return (
        g,
        rot[0, 0] * l0 + rot[0, 1] * l1 + rot[0, 2] * l2,
        rot[1, 0] * l0 + rot[1, 1] * l1 + rot[1, 2] * l2,
        rot[2, 0] * l0 + rot[2, 1] * l1 + rot[2, 2] * l2,
    )


def body_contacts(
    pos: np.ndarray,
    radii: np.ndarray,
    margin: np.ndarray,
    kind: np.ndarray,
    bpos: np.ndarray,
    brot: np.ndarray,
    bext: np.ndarray,
    bnormal: np.ndarray,
    awake: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sphere–plane and sphere–box contacts with a gap below ``margin`` (N,) m, of the spheres
    awake (``awake`` (N,) bool; None: every sphere): one asleep is held still, so its contacts
    with bodies have nothing to solve.

    Returns sphere slot (M,), body index (M,), normal (M, 3) out of the body, overlap (M,) m,
    ordered by slot, then body. On one numba thread the spheres are tested once; on more, twice (count, then fill); both give the same arrays.
    """
    mask = np.zeros(0, dtype=np.bool_) if awake is None else awake
    args = (pos, radii, margin, kind, bpos, brot, bext, bnormal, mask)
    if numba.get_num_threads() == 1:
        return body_contacts_serial(*args)
    return body_contacts_parallel(*args)


@njit(cache=True)
def body_contacts_serial(pos, radii, margin, kind, bpos, brot, bext, bnormal, awake):
    """:func:`body_contacts` in one pass into buffers sized for every sphere touching every
    body (memory that is reserved, not touched, beyond the hits)."""
    n = pos.shape[0]
    nb = kind.shape[0]
    si = np.empty(n * nb, dtype=np.int64)
    sb = np.empty(n * nb, dtype=np.int64)
    nrm = np.empty((n * nb, 3))
    gap = np.empty(n * nb)
    bound = np.sqrt(bext[:, 0] * bext[:, 0] + bext[:, 1] * bext[:, 1] + bext[:, 2] * bext[:, 2])
    k = 0
    every = awake.shape[0] == 0
    for i in range(n):
        if not (every or awake[i]):
            continue
        x0, x1, x2, ri, mi = pos[i, 0], pos[i, 1], pos[i, 2], radii[i], margin[i]
        for b in range(nb):
            # The plane test and the box's bounding-sphere cull of _body_test, on scalars:
            # only boxes' near spheres pay for the full test.
            d0, d1, d2 = x0 - bpos[b, 0], x1 - bpos[b, 1], x2 - bpos[b, 2]
            if kind[b] == PLANE:
                n0, n1, n2 = bnormal[b, 0], bnormal[b, 1], bnormal[b, 2]
                g = ri - (d0 * n0 + d1 * n1 + d2 * n2)
            else:
                reach = ri + mi + bound[b]
                if d0 * d0 + d1 * d1 + d2 * d2 > reach * reach:
                    continue
                g, n0, n1, n2 = _body_test(
                    pos[i], ri, mi, kind[b], bpos[b], brot[b], bext[b], bnormal[b]
                )
            if g > -mi:
                si[k] = i
                sb[k] = b
                nrm[k, 0], nrm[k, 1], nrm[k, 2] = n0, n1, n2
                gap[k] = g
                k += 1
    return si[:k], sb[:k], nrm[:k], gap[:k]


@njit(parallel=True, cache=True)
def body_contacts_parallel(pos, radii, margin, kind, bpos, brot, bext, bnormal, awake):
    """:func:`body_contacts` by count, then fill, each pass over the spheres in parallel."""
    n = pos.shape[0]
    nb = kind.shape[0]
    counts = np.zeros(n + 1, dtype=np.int64)
    every = awake.shape[0] == 0
    for i in prange(n):
        c = 0
        for b in range(nb if every or awake[i] else 0):
            g, _, _, _ = _body_test(
                pos[i], radii[i], margin[i], kind[b], bpos[b], brot[b], bext[b], bnormal[b]
            )
            if g > -margin[i]:
                c += 1
        counts[i + 1] = c
    off, si, sb, nrm, gap = hit_buffers(counts)
    for i in prange(n):
        k = off[i]
        for b in range(nb if every or awake[i] else 0):
            g, n0, n1, n2 = _body_test(
                pos[i], radii[i], margin[i], kind[b], bpos[b], brot[b], bext[b], bnormal[b]
            )
            if g > -margin[i]:
                si[k] = i
                sb[k] = b
                nrm[k, 0], nrm[k, 1], nrm[k, 2] = n0, n1, n2
                gap[k] = g
                k += 1
    return si, sb, nrm, gap


@njit(parallel=True, cache=True)
def assemble(
    pi,
    pj,
    pn,
    pg,
    bi,
    bb,
    bn,
    bg,
    slab,
    n_slabs,
    awake,
    pos,
    vel,
    radii,
    invm,
    invI,
    mu,
    mur,
    bpos,
    bvel,
    bang,
    bmu,
    h,
    upsilon,
    estar,
    soft=1.0,
):
    """Order the contacts for the partitioned sweep and compute their row constants.

    Group s < S holds contacts inside slab s (and all body contacts of its spheres); group
    S + s holds contacts between slabs s and s + 1; group 2S holds the frozen contacts, of a
    sleeping sphere (``awake`` (N,) False) with a sleeping sphere or a body, which the solver
    leaves as they are (their warm-start multipliers kept). ``invm``/``invI`` are 0 for a
    sleeping sphere (a fixed obstacle to the awake ones); the compliance of a Hertz row between
    an awake and a sleeping sphere is ``soft`` (≥ 1) times its own, for the bed the sleeper
    stands for yields behind it (``solver.active_zone.sleeper_compliance``; 1 without the zone).
    Returns i (Nc,), j (Nc,), the table (Nc, NCOL), overlap (Nc,) and group offsets (2S + 2,).
    """
    mp = pi.shape[0]
    mt = mp + bi.shape[0]
    group = np.empty(mt, dtype=np.int64)
    frozen = 2 * n_slabs
    for k in range(mt):
        if k < mp:
            si = slab[pi[k]]
            sj = slab[pj[k]]
            group[k] = si if si == sj else n_slabs + min(si, sj)
            if not (awake[pi[k]] or awake[pj[k]]):
                group[k] = frozen
        else:
            group[k] = slab[bi[k - mp]] if awake[bi[k - mp]] else frozen
    start = np.zeros(2 * n_slabs + 2, dtype=np.int64)
    for k in range(mt):
        start[group[k] + 1] += 1
    for g in range(2 * n_slabs + 1):
        start[g + 1] += start[g]
    fill = start[:-1].copy()
    src = np.empty(mt, dtype=np.int64)
    for k in range(mt):
        src[fill[group[k]]] = k
        fill[group[k]] += 1

    ci = np.empty(mt, dtype=np.int64)
    cj = np.empty(mt, dtype=np.int64)
    cd = np.empty((mt, NCOL))  # every column written below: no zeroing pass over the table
    gap = np.empty(mt)
    for k in prange(mt):
        s = src[k]
        if s < mp:
            i, j, g = pi[s], pj[s], pg[s]
            for a in range(3):
                cd[k, N0 + a] = pn[s, a]
            rstar = radii[i] * radii[j] / (radii[i] + radii[j])
            cd[k, RJ] = radii[j] - 0.5 * max(g, 0.0)
            cd[k, MU] = 0.5 * (mu[i] + mu[j])
            cd[k, MUR] = rstar * 0.5 * (mur[i] + mur[j])
            for a in range(6):
                cd[k, VB + a] = 0.0  # VB, WB: no body
            imj, iij = invm[j], invI[j]
        else:
            t = s - mp
            i, b, g = bi[t], bb[t], bg[t]
            j = -(b + 1)
            for a in range(3):
                cd[k, N0 + a] = bn[t, a]
            rstar = radii[i]
            cd[k, RJ] = 0.0
            cd[k, MU] = bmu[b]
            cd[k, MUR] = rstar * mur[i]
            imj, iij = 0.0, 0.0
            rib = radii[i] - 0.5 * max(g, 0.0)
            # Velocity of the body's material point at the contact.
            arm0 = pos[i, 0] - rib * bn[t, 0] - bpos[b, 0]
            arm1 = pos[i, 1] - rib * bn[t, 1] - bpos[b, 1]
            arm2 = pos[i, 2] - rib * bn[t, 2] - bpos[b, 2]
            w0, w1, w2 = bang[b, 0], bang[b, 1], bang[b, 2]
            cd[k, VB + 0] = bvel[b, 0] + w1 * arm2 - w2 * arm1
            cd[k, VB + 1] = bvel[b, 1] + w2 * arm0 - w0 * arm2
            cd[k, VB + 2] = bvel[b, 2] + w0 * arm1 - w1 * arm0
            cd[k, WB + 0] = w0
            cd[k, WB + 1] = w1
            cd[k, WB + 2] = w2
        ci[k] = i
        cj[k] = j
        gap[k] = g
        ri = radii[i] - 0.5 * max(g, 0.0)
        cd[k, RI] = ri
        rj = cd[k, RJ]
        sn = invm[i] + imj
        cd[k, KT] = _inverse(sn + ri * ri * invI[i] + rj * rj * iij)
        cd[k, KR] = _inverse(invI[i] + iij)
        un0 = 0.0
        for a in range(3):
            vj = vel[j, a] if j >= 0 else cd[k, VB + a]
            un0 += cd[k, N0 + a] * (vel[i, a] - vj)
        if g < -1e-6 * rstar:
            # Speculative: may close the gap within the step, not more. A pair it stopped at
            # touching (|g| ~ rounding) is handed to the compliant row below next step.
            sig = 0.0
            rhs = g / h
        elif estar <= 0.0:  # stiff
            sig = 0.0
            rhs = 4.0 * upsilon / h * g + upsilon * un0
        else:
            # Hertz-mapped row (docs/physics.md) divided by its Jacobian factor (5/4) g^(1/4):
            # an effective compliance 4 / (5 k_n √g) on the plain normal row and φ = (4/5) g.
            # The compliance is taken at the overlap the pair reaches by the end of the step
            # if it keeps approaching: evaluated at the current g, a fast pair meeting a
            # near-zero stiffness would sink in by a whole step's travel.
            kn = 4.0 / 3.0 * estar * np.sqrt(rstar)
            eps = 4.0 / (5.0 * kn * np.sqrt(max(g - h * un0, g, 1e-9 * rstar)))
            if j >= 0 and not (awake[i] and awake[j]):
                eps *= soft
            sig = 4.0 * upsilon * eps / (h * h)
            rhs = 4.0 * upsilon / h * 0.8 * g + upsilon * un0
        cd[k, SIG] = sig
        cd[k, B] = rhs
        cd[k, KN] = _inverse(sn + sig)
    return ci, cj, cd, gap, start


@njit(cache=True, inline="always")
def _inverse(a):
    """1/a, and 0 for a = 0 (a frozen row between fixed obstacles: never solved)."""
    return 1.0 / a if a > 0.0 else 0.0


@njit(cache=True)
def body_loads(ci, cj, cd, lam, pos, bpos, nb, h):
    """Force (nb, 3) in N and torque about each body's centre (nb, 3) in N·m from the particles."""
    force = np.zeros((nb, 3))
    torque = np.zeros((nb, 3))
    for k in range(ci.shape[0]):
        if cj[k] >= 0:
            continue
        b = -cj[k] - 1
        i = ci[k]
        n0, n1, n2 = cd[k, N0], cd[k, N0 + 1], cd[k, N0 + 2]
        f0 = -(lam[k, 0] * n0 + lam[k, 1]) / h
        f1 = -(lam[k, 0] * n1 + lam[k, 2]) / h
        f2 = -(lam[k, 0] * n2 + lam[k, 3]) / h
        a0 = pos[i, 0] - cd[k, RI] * n0 - bpos[b, 0]
        a1 = pos[i, 1] - cd[k, RI] * n1 - bpos[b, 1]
        a2 = pos[i, 2] - cd[k, RI] * n2 - bpos[b, 2]
        force[b, 0] += f0
        force[b, 1] += f1
        force[b, 2] += f2
        torque[b, 0] += a1 * f2 - a2 * f1 - lam[k, 4] / h
        torque[b, 1] += a2 * f0 - a0 * f2 - lam[k, 5] / h
        torque[b, 2] += a0 * f1 - a1 * f0 - lam[k, 6] / h
    return force, torque
