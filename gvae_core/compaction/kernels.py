"""Compiled CPU kernels of compaction (Numba, the renderer's `rendering.kernels.kernel`: no GIL,
cached on disk), driven in threads by `compaction.compiled`.

Each is the loop form of the numpy or torch code beside it, which stays the reference the tests
hold it to: `tile_hits` of `scoring`'s torch sweep (`pixel_hits`, `frame_hits`), `gaussian_moments`
of `moments.moments`, `pair_costs` and `merge_pairs` of `moments.pair_cost` and `merge_pairs`,
`greedy_matching` of `graph.matching`, `group_sums` of the reductions of `merge.merge_groups`,
`eigh3` of numpy's eigh (up to each axis's sign), `brute_neighbours` of scipy's k-d tree. The
formulas and the order of every sum are the reference's; they differ from it by float rounding
only (fused multiply-adds, the C library's exp and log). Imported on first use (it imports Numba).
"""

from __future__ import annotations

import math

import numpy as np

from ..rendering.kernels import ALPHA_MAX, ALPHA_MIN, CA, CB, CC, MX, MY, OP, T_MIN, inline, kernel

f32 = np.float32
_ZERO, _ONE, _HALF = f32(0.0), f32(1.0), f32(0.5)
_EXP_LO = f32(-87.0)
_OPACITY_FLOOR = f32(1e-30)


# ------------------------------------------------------------------------------ pixel hits

@kernel
def tile_hits(table, ids, offsets, t_lo, t_hi, tiles_x, ts, width, height, wanted, pair_hits):
    """For tiles t_lo..t_hi-1, pair_hits[k] = the pixels inside the image into which pair k's
    Gaussian (`ids[k]`, a row of the packed `table`) is composited (alpha >= 1/255, before the pixel
    stops: `rasterize`'s rules). With `wanted` (a bool per table row; empty: every tile) only the
    tiles that list a wanted row are swept; the other pairs, and those past a tile's stop, are left
    as they are (zeros)."""
    p_count = ts * ts
    trans = np.empty(p_count, np.float32)
    live = np.empty(p_count, np.float32)
    inside = np.empty(p_count, np.bool_)
    px = np.empty(p_count, np.float32)
    py = np.empty(p_count, np.float32)
    for p in range(p_count):
        px[p] = f32(p % ts) + _HALF
        py[p] = f32(p // ts) + _HALF
    for t in range(t_lo, t_hi):
        start, end = offsets[t], offsets[t + 1]
        if end == start:
            continue
        if wanted.shape[0]:
            sweep = False
            for k in range(start, end):
                if wanted[ids[k]]:
                    sweep = True
                    break
            if not sweep:
                continue
        xt, yt = (t % tiles_x) * ts, (t // tiles_x) * ts
        x0, y0 = f32(xt), f32(yt)
        for p in range(p_count):
            inside[p] = xt + p % ts < width and yt + p // ts < height
            trans[p] = _ONE
            live[p] = _ONE
        n_live = p_count
        for k in range(start, end):
            g = ids[k]
            mx, my = table[g, MX] - x0, table[g, MY] - y0
            ha, nb, hc = -_HALF * table[g, CA], -table[g, CB], -_HALF * table[g, CC]
            lo = np.log(max(table[g, OP], _OPACITY_FLOOR))
            count = 0
            stopped = 0
            for p in range(p_count):
                dx = px[p] - mx
                dy = py[p] - my
                e = lo + dx * (ha * dx + nb * dy) + hc * dy * dy
                e = min(max(e, _EXP_LO), _ZERO)
                alpha = min(np.exp(e), ALPHA_MAX)
                alpha = alpha if alpha >= ALPHA_MIN else _ZERO
                tr = trans[p]
                after = tr - tr * alpha
                keep = live[p] if after >= T_MIN else _ZERO
                w = keep * alpha * tr
                count += np.int32(w > _ZERO and inside[p])
                stopped += np.int32(live[p] > keep)
                trans[p] = after if keep > _ZERO else tr
                live[p] = keep
            pair_hits[k] = count
            n_live -= stopped
            if n_live == 0:
                break


@kernel
def add_pair_hits(pair_hits, ids, hits):
    """hits[ids[k]] += pair_hits[k] for every pair k."""
    for k in range(ids.shape[0]):
        hits[ids[k]] += pair_hits[k]


# ------------------------------------------------------------------------------ moments

@inline
def _gram(a0, a1, a2, b0, b1, b2, c0, c1, c2, floor):
    """The covariance M M^T + floor I of M = rows (a, b, c) (a rotation times the scales), packed
    (xx, xy, xz, yy, yz, zz)."""
    return (a0 * a0 + a1 * a1 + a2 * a2 + floor, a0 * b0 + a1 * b1 + a2 * b2, a0 * c0 + a1 * c1 + a2 * c2,
            b0 * b0 + b1 * b1 + b2 * b2 + floor, b0 * c0 + b1 * c1 + b2 * c2, c0 * c0 + c1 * c1 + c2 * c2 + floor)


@kernel
def gaussian_moments(rows, means, log_scales, quats, opacity, center, floor, ls_lo, ls_hi, lo, hi,
                     mu, sigma, mass, log_det):
    """For i in lo..hi-1, of the Gaussian rows[i] (float64): mu[i] = its centre less `center`,
    sigma[i] its packed covariance R diag(exp(2 clamped log-scale)) R^T plus `floor` on the
    diagonal (R of its normalised quaternion w, x, y, z, the identity for a zero or non-finite one),
    mass[i] = opacity[i] (activated) x sqrt(the sum of the covariance's 2x2 principal minors) and
    log_det[i] = log max(det, 1e-300)."""
    for i in range(lo, hi):
        r = rows[i]
        qw, qx, qy, qz = (np.float64(quats[r, 0]), np.float64(quats[r, 1]), np.float64(quats[r, 2]),
                          np.float64(quats[r, 3]))
        norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if math.isfinite(norm) and norm > 1e-12:
            qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
        else:
            qw, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
        r00, r01, r02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
        r10, r11, r12 = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
        r20, r21, r22 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)
        s0 = math.exp(min(max(np.float64(log_scales[r, 0]), ls_lo), ls_hi))
        s1 = math.exp(min(max(np.float64(log_scales[r, 1]), ls_lo), ls_hi))
        s2 = math.exp(min(max(np.float64(log_scales[r, 2]), ls_lo), ls_hi))
        a0, a1, a2 = r00 * s0, r01 * s1, r02 * s2
        b0, b1, b2 = r10 * s0, r11 * s1, r12 * s2
        c0, c1, c2 = r20 * s0, r21 * s1, r22 * s2
        xx, xy, xz, yy, yz, zz = _gram(a0, a1, a2, b0, b1, b2, c0, c1, c2, floor)
        sigma[i, 0], sigma[i, 1], sigma[i, 2], sigma[i, 3], sigma[i, 4], sigma[i, 5] = xx, xy, xz, yy, yz, zz
        minors = xx * yy - xy * xy + xx * zz - xz * xz + yy * zz - yz * yz
        mass[i] = opacity[r] * math.sqrt(max(minors, 0.0))
        d = xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)
        log_det[i] = math.log(max(d, 1e-300))
        for c in range(3):
            mu[i, c] = np.float64(means[r, c]) - center[c]


@inline
def _merged(mass, mu, sigma, i, j):
    """The mass, the weights wa, wb (and wa wb) and the covariance (xx, xy, xz, yy, yz, zz) of
    Gaussians i and j merged into one (moment matching)."""
    ma, mb = mass[i], mass[j]
    total = max(ma + mb, 1e-300)
    wa = ma / total
    wb = 1.0 - wa
    ww = wa * wb
    dx, dy, dz = mu[i, 0] - mu[j, 0], mu[i, 1] - mu[j, 1], mu[i, 2] - mu[j, 2]
    xx = wa * sigma[i, 0] + wb * sigma[j, 0] + ww * (dx * dx)
    xy = wa * sigma[i, 1] + wb * sigma[j, 1] + ww * (dx * dy)
    xz = wa * sigma[i, 2] + wb * sigma[j, 2] + ww * (dx * dz)
    yy = wa * sigma[i, 3] + wb * sigma[j, 3] + ww * (dy * dy)
    yz = wa * sigma[i, 4] + wb * sigma[j, 4] + ww * (dy * dz)
    zz = wa * sigma[i, 5] + wb * sigma[j, 5] + ww * (dz * dz)
    return total, wa, wb, ww, xx, xy, xz, yy, yz, zz


@kernel
def pair_costs(mass, mu, sigma, log_det, colour, weight, a, b, colour_weight, lo, hi, out):
    """out[e] for e in lo..hi-1: the cost of merging a[e] and b[e] (`moments.pair_cost`)."""
    for e in range(lo, hi):
        i, j = a[e], b[e]
        total, wa, wb, ww, xx, xy, xz, yy, yz, zz = _merged(mass, mu, sigma, i, j)
        d = xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)
        shape = 0.5 * (math.log(max(d, 1e-300)) - wa * log_det[i] - wb * log_det[j])
        c0, c1, c2 = colour[i, 0] - colour[j, 0], colour[i, 1] - colour[j, 1], colour[i, 2] - colour[j, 2]
        col = ww * (c0 * c0 + c1 * c1 + c2 * c2)
        out[e] = (weight[i] + weight[j]) * total * (max(shape, 0.0) + colour_weight * col)


@kernel
def merge_pairs(mass, mu, sigma, log_det, colour, weight, a, b):
    """Merge each b[e] into a[e] in place (`moments.merge_pairs`; the pairs disjoint)."""
    for e in range(a.shape[0]):
        i, j = a[e], b[e]
        total, wa, wb, ww, xx, xy, xz, yy, yz, zz = _merged(mass, mu, sigma, i, j)
        sigma[i, 0], sigma[i, 1], sigma[i, 2], sigma[i, 3], sigma[i, 4], sigma[i, 5] = xx, xy, xz, yy, yz, zz
        d = xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)
        log_det[i] = math.log(max(d, 1e-300))
        for c in range(3):
            mu[i, c] = wa * mu[i, c] + wb * mu[j, c]
            colour[i, c] = wa * colour[i, c] + wb * colour[j, c]
        mass[i] = total
        weight[i] = weight[i] + weight[j]


# ------------------------------------------------------------------------------ matching

@inline
def _before(cost, e, f):
    """Whether edge e comes before edge f in the stable ascending order of `cost` (NaN last)."""
    ce, cf = cost[e], cost[f]
    if ce != ce:
        return cf != cf and e < f
    if cf != cf:
        return True
    return ce < cf or (ce == cf and e < f)


@kernel
def greedy_matching(a, b, cost, n, limit, rounds, chosen):
    """`graph.matching`'s rounds: chosen[e] = True for every edge taken (each round, the live edges
    that come first of both their ends' live edges in the stable order of `cost`), for `rounds`
    rounds or until `limit` edges. Returns how many."""
    free = np.ones(n, np.bool_)
    best = np.empty(n, np.int64)
    total = 0
    for _ in range(rounds):
        best[:] = -1
        live = 0
        for e in range(a.shape[0]):
            i, j = a[e], b[e]
            if free[i] and free[j]:
                live += 1
                if best[i] < 0 or _before(cost, e, best[i]):
                    best[i] = e
                if best[j] < 0 or _before(cost, e, best[j]):
                    best[j] = e
        if live == 0:
            break
        picked = 0
        for e in range(a.shape[0]):
            i, j = a[e], b[e]
            if free[i] and free[j] and best[i] == e and best[j] == e:
                chosen[e] = True
                picked += 1
        for e in range(a.shape[0]):
            if chosen[e]:
                free[a[e]] = False
                free[b[e]] = False
        total += picked
        if total >= limit:
            break
    return total


# ------------------------------------------------------------------------------ merged groups

@kernel
def group_sums(starts, ends, rows, mass, mu, sigma, opacity, sh_dc, sh_rest, lo, hi, w, heaviest, g_mass, g_mu,
               g_sigma, together, g_dc, g_rest):
    """For groups j in lo..hi-1 (members starts[j]..ends[j]-1: float64 moments mass, mu, sigma, and
    the rows `rows` of the cloud's activated opacity and float32 SH): the mass weight w of each
    member (its mass / the group's), the group's mass, mass-weighted centre and covariance (the
    members' covariances about the group's centre), what its members draw together
    (1 - prod(1 - o)) and its mass-weighted SH (float32 weights and sums, as `merge_groups`), each
    sum in member order; and its heaviest member's row (`merge.representatives`: the first of the
    heaviest, the members being in ascending rows)."""
    k_rest = sh_rest.shape[1]
    for j in range(lo, hi):
        s, t = starts[j], ends[j]
        m = 0.0
        top = s
        for i in range(s, t):
            m += mass[i]
            if mass[i] > mass[top]:
                top = i
        heaviest[j] = rows[top]
        g_mass[j] = m
        total = max(m, 1e-300)
        cx = cy = cz = 0.0
        for i in range(s, t):
            wi = mass[i] / total
            w[i] = wi
            cx += wi * mu[i, 0]
            cy += wi * mu[i, 1]
            cz += wi * mu[i, 2]
        g_mu[j, 0], g_mu[j, 1], g_mu[j, 2] = cx, cy, cz
        q0 = q1 = q2 = q3 = q4 = q5 = 0.0
        log_clear = 0.0
        for c in range(3):
            g_dc[j, c] = f32(0.0)
        for r in range(k_rest):
            for c in range(3):
                g_rest[j, r, c] = f32(0.0)
        for i in range(s, t):
            wi = w[i]
            dx, dy, dz = mu[i, 0] - cx, mu[i, 1] - cy, mu[i, 2] - cz
            q0 += wi * (sigma[i, 0] + dx * dx)
            q1 += wi * (sigma[i, 1] + dx * dy)
            q2 += wi * (sigma[i, 2] + dx * dz)
            q3 += wi * (sigma[i, 3] + dy * dy)
            q4 += wi * (sigma[i, 4] + dy * dz)
            q5 += wi * (sigma[i, 5] + dz * dz)
            row = rows[i]
            log_clear += math.log1p(-min(opacity[row], 1.0 - 1e-12))
            w32 = f32(wi)
            for c in range(3):
                g_dc[j, c] += w32 * sh_dc[row, c]
            for r in range(k_rest):
                for c in range(3):
                    g_rest[j, r, c] += w32 * sh_rest[row, r, c]
        g_sigma[j, 0], g_sigma[j, 1], g_sigma[j, 2] = q0, q1, q2
        g_sigma[j, 3], g_sigma[j, 4], g_sigma[j, 5] = q3, q4, q5
        together[j] = -math.expm1(log_clear)


# ------------------------------------------------------------------------------ the neighbour graph

@kernel
def unique_edges(nb, a_out, b_out):
    """The edges (a < b, each once, ascending by a then b) between each row i of nb (M, k+1) and
    its neighbours nb[i, 1:] (entries >= M, or i itself, left out), written into a_out, b_out
    (at least M k long). Returns how many (`graph.knn_edges`' np.unique of the keys a M + b)."""
    m = nb.shape[0]
    count = np.zeros(m + 1, np.int64)
    for i in range(m):
        for j in range(1, nb.shape[1]):
            b = nb[i, j]
            if b < m and b != i:
                count[min(i, b) + 1] += 1
    for i in range(m):
        count[i + 1] += count[i]
    cursor = count[:m].copy()
    hi = np.empty(count[m], np.int64)
    for i in range(m):
        for j in range(1, nb.shape[1]):
            b = nb[i, j]
            if b < m and b != i:
                lo = min(i, b)
                hi[cursor[lo]] = max(i, b)
                cursor[lo] += 1
    out = 0
    for lo in range(m):
        s, t = count[lo], count[lo + 1]
        for x in range(s + 1, t):  # insertion sort of the (few) larger ends
            v = hi[x]
            y = x - 1
            while y >= s and hi[y] > v:
                hi[y + 1] = hi[y]
                y -= 1
            hi[y + 1] = v
        for x in range(s, t):
            if x == s or hi[x] != hi[x - 1]:
                a_out[out] = lo
                b_out[out] = hi[x]
                out += 1
    return out


@kernel
def shapes(vals, vecs, floor, mass, together, ls_lo, ls_hi, lo, hi, log_scale, quats, logits):
    """For merged Gaussians j in lo..hi-1, from the eigen-decomposition (vals, vecs) of their
    covariances: log-scales (of vals less `floor`, clamped), the rotation of vecs (its first axis
    flipped where it is a reflection) as a quaternion (Shepperd's method, w >= 0,
    `quaternions.from_rotmat`) and the opacity logit that keeps `mass` for the stored shape (plus
    `floor`), at most `together`, in [1e-6, 1 - 1e-6] (`merge.write_shapes`)."""
    for j in range(lo, hi):
        v = vecs[j]
        d = (v[0, 0] * (v[1, 1] * v[2, 2] - v[1, 2] * v[2, 1]) - v[0, 1] * (v[1, 0] * v[2, 2] - v[1, 2] * v[2, 0])
             + v[0, 2] * (v[1, 0] * v[2, 1] - v[1, 1] * v[2, 0]))
        f = -1.0 if d < 0 else 1.0
        a00, a10, a20 = f * v[0, 0], f * v[1, 0], f * v[2, 0]
        a01, a11, a21 = v[0, 1], v[1, 1], v[2, 1]
        a02, a12, a22 = v[0, 2], v[1, 2], v[2, 2]
        s0 = min(max(0.5 * math.log(max(vals[j, 0] - floor, 1e-300)), ls_lo), ls_hi)
        s1 = min(max(0.5 * math.log(max(vals[j, 1] - floor, 1e-300)), ls_lo), ls_hi)
        s2 = min(max(0.5 * math.log(max(vals[j, 2] - floor, 1e-300)), ls_lo), ls_hi)
        log_scale[j, 0], log_scale[j, 1], log_scale[j, 2] = s0, s1, s2
        e0, e1, e2 = math.exp(s0), math.exp(s1), math.exp(s2)
        b00, b01, b02 = a00 * e0, a01 * e1, a02 * e2
        b10, b11, b12 = a10 * e0, a11 * e1, a12 * e2
        b20, b21, b22 = a20 * e0, a21 * e1, a22 * e2
        xx, xy, xz, yy, yz, zz = _gram(b00, b01, b02, b10, b11, b12, b20, b21, b22, floor)
        minors = xx * yy - xy * xy + xx * zz - xz * xz + yy * zz - yz * yz
        o = mass[j] / max(math.sqrt(max(minors, 0.0)), 1e-300)
        o = min(max(min(o, together[j]), 1e-6), 1.0 - 1e-6)
        logits[j] = math.log(o / (1.0 - o))
        # Shepperd: column p of K = 4 q q^T, p the largest of (trace, a00, a11, a22)
        diag = (a00 + a11 + a22, a00, a11, a22)
        p = 0
        for c in range(1, 4):
            if diag[c] > diag[p]:
                p = c
        if p == 0:
            k0, k1, k2, k3 = 1 + a00 + a11 + a22, a21 - a12, a02 - a20, a10 - a01
        elif p == 1:
            k0, k1, k2, k3 = a21 - a12, 1 + a00 - a11 - a22, a01 + a10, a02 + a20
        elif p == 2:
            k0, k1, k2, k3 = a02 - a20, a01 + a10, 1 - a00 + a11 - a22, a12 + a21
        else:
            k0, k1, k2, k3 = a10 - a01, a02 + a20, a12 + a21, 1 - a00 - a11 + a22
        kp = (k0, k1, k2, k3)[p]
        s = math.sqrt(max(kp, 1e-300)) * 2
        q0, q1, q2, q3 = k0 / s, k1 / s, k2 / s, k3 / s
        if p == 0:
            q0 = 0.25 * s
        elif p == 1:
            q1 = 0.25 * s
        elif p == 2:
            q2 = 0.25 * s
        else:
            q3 = 0.25 * s
        if q0 < 0:
            q0, q1, q2, q3 = -q0, -q1, -q2, -q3
        norm = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        quats[j, 0], quats[j, 1], quats[j, 2], quats[j, 3] = q0 / norm, q1 / norm, q2 / norm, q3 / norm


@kernel
def eigh3(sigma, lo, hi, vals, vecs):
    """For j in lo..hi-1, the eigen-decomposition of the symmetric 3x3 matrix packed in sigma[j]
    (xx, xy, xz, yy, yz, zz): vals[j] ascending and vecs[j] their unit eigenvectors as columns,
    as numpy's eigh gives them (up to each column's sign, and the axes of equal eigenvalues), by
    cyclic Jacobi rotations (Numerical Recipes' `jacobi`: to the float64 precision of the
    matrix, in a few sweeps) -- LAPACK called once per 3x3 matrix costs 30 times as long."""
    a = np.empty((3, 3))
    v = np.empty((3, 3))
    for j in range(lo, hi):
        a[0, 0], a[0, 1], a[0, 2] = sigma[j, 0], sigma[j, 1], sigma[j, 2]
        a[1, 1], a[1, 2], a[2, 2] = sigma[j, 3], sigma[j, 4], sigma[j, 5]
        for r in range(3):
            for s in range(3):
                v[r, s] = 1.0 if r == s else 0.0
        for sweep in range(50):
            off = abs(a[0, 1]) + abs(a[0, 2]) + abs(a[1, 2])
            if off == 0.0:
                break
            tresh = 0.2 * off / 9.0 if sweep < 3 else 0.0
            for p in range(2):
                for q in range(p + 1, 3):
                    apq = a[p, q]
                    g = 100.0 * abs(apq)
                    if sweep > 3 and abs(a[p, p]) + g == abs(a[p, p]) and abs(a[q, q]) + g == abs(a[q, q]):
                        a[p, q] = 0.0
                    elif abs(apq) > tresh:
                        h = a[q, q] - a[p, p]
                        if abs(h) + g == abs(h):
                            t = apq / h
                        else:
                            theta = 0.5 * h / apq
                            t = 1.0 / (abs(theta) + math.sqrt(1.0 + theta * theta))
                            if theta < 0.0:
                                t = -t
                        cs = 1.0 / math.sqrt(1.0 + t * t)
                        sn = t * cs
                        tau = sn / (1.0 + cs)
                        h = t * apq
                        a[p, p] -= h
                        a[q, q] += h
                        a[p, q] = 0.0
                        r = 3 - p - q  # the third axis: (p, r) and (r, q) or (r, p) as stored (upper)
                        arp = a[min(r, p), max(r, p)]
                        arq = a[min(r, q), max(r, q)]
                        a[min(r, p), max(r, p)] = arp - sn * (arq + arp * tau)
                        a[min(r, q), max(r, q)] = arq + sn * (arp - arq * tau)
                        for row in range(3):
                            vrp, vrq = v[row, p], v[row, q]
                            v[row, p] = vrp - sn * (vrq + vrp * tau)
                            v[row, q] = vrq + sn * (vrp - vrq * tau)
        # ascending, the columns with them
        o0, o1, o2 = 0, 1, 2
        if a[o1, o1] < a[o0, o0]:
            o0, o1 = o1, o0
        if a[o2, o2] < a[o1, o1]:
            o1, o2 = o2, o1
            if a[o1, o1] < a[o0, o0]:
                o0, o1 = o1, o0
        vals[j, 0], vals[j, 1], vals[j, 2] = a[o0, o0], a[o1, o1], a[o2, o2]
        for r in range(3):
            vecs[j, r, 0], vecs[j, r, 1], vecs[j, r, 2] = v[r, o0], v[r, o1], v[r, o2]


_HASH = np.int64(-7046029254386353131)  # 0x9E3779B97F4A7C15 (Fibonacci hashing) as an int64


@kernel
def cell_table(keys, slots):
    """An open-addressing hash table of the cells' keys (sorted, unique): slots (S,) int64, S a
    power of two >= 2 len(keys), each the index of a key or -1."""
    mask = slots.shape[0] - 1
    shift = 64 - _bits(slots.shape[0])
    slots[:] = -1
    for c in range(keys.shape[0]):
        h = (keys[c] * _HASH) >> shift & mask
        while slots[h] >= 0:
            h = (h + 1) & mask
        slots[h] = c


@inline
def _bits(size):
    """log2 of a power of two."""
    b = 0
    while (1 << b) < size:
        b += 1
    return b


@inline
def _find(keys, slots, key, shift):
    """The index of `key` in the cell table (`cell_table`), or -1 (the hash: the top bits)."""
    mask = slots.shape[0] - 1
    h = (key * _HASH) >> shift & mask
    while slots[h] >= 0:
        if keys[slots[h]] == key:
            return slots[h]
        h = (h + 1) & mask
    return -1


@inline
def _take(best_d, best_t, d, u):
    """Put candidate u at squared distance d (nearer than the last of best_d) into the sorted lists
    best_d, best_t of the nearest so far, after those at equal distances."""
    v = best_d.shape[0] - 1
    while v > 0 and best_d[v - 1] > d:
        best_d[v] = best_d[v - 1]
        best_t[v] = best_t[v - 1]
        v -= 1
    best_d[v] = d
    best_t[v] = u


#: The 27 cells around a cell (offsets dx, dy, dz), nearest first: its own, faces, edges, corners.
_AROUND = np.array(sorted(((x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)),
                          key=lambda o: abs(o[0]) + abs(o[1]) + abs(o[2])), np.int64)


@kernel
def cell_neighbours(sorted_points, perm, cell_ix, keys, starts, slots, origin, h, dims, k, lo, hi, nb, certain):
    """The k nearest others of each point of cells lo..hi-1 among the points of the 3 x 3 x 3
    cells around its own (the points sorted by cell: sorted_points, the original index of each
    perm; cells' first points starts, integer coordinates cell_ix, keys ix << 42 | iy << 21 | iz,
    found through the hash table slots; cell edge h, from origin, dims cells a side; a cell
    farther than the k-th nearest so far is skipped): nb[i] (k, original indices) nearest first
    (ties: the first seen, cells nearest first), and certain[i] whether no point outside those
    cells can be nearer than the k-th (else the caller asks an exact search)."""
    best_d = np.empty(k)
    best_t = np.empty(k, np.int64)
    shift = 64 - _bits(slots.shape[0])
    first = np.empty(27, np.int64)
    last = np.empty(27, np.int64)
    offs = np.empty((27, 3), np.int64)
    box_lo = np.empty(3)
    bound_lo = np.empty(3)
    bound_hi = np.empty(3)
    for c in range(lo, hi):
        used = 0
        for o in range(27):
            x, y, z = cell_ix[c, 0] + _AROUND[o, 0], cell_ix[c, 1] + _AROUND[o, 1], cell_ix[c, 2] + _AROUND[o, 2]
            if x < 0 or y < 0 or z < 0 or x >= dims[0] or y >= dims[1] or z >= dims[2]:
                continue
            f = _find(keys, slots, (x << 42) | (y << 21) | z, shift)
            if f < 0:
                continue
            first[used], last[used] = starts[f], starts[f + 1]
            offs[used, 0], offs[used, 1], offs[used, 2] = _AROUND[o, 0], _AROUND[o, 1], _AROUND[o, 2]
            used += 1
        # the cell's box, and the faces of the 3 x 3 x 3 block with cells beyond them
        for a in range(3):
            ci = cell_ix[c, a]
            box_lo[a] = origin[a] + ci * h
            bound_lo[a] = origin[a] + (ci - 1) * h if ci - 1 > 0 else -np.inf
            bound_hi[a] = origin[a] + (ci + 2) * h if ci + 2 < dims[a] else np.inf
        for s in range(starts[c], starts[c + 1]):
            px, py, pz = sorted_points[s, 0], sorted_points[s, 1], sorted_points[s, 2]
            for j in range(k):
                best_d[j] = np.inf
                best_t[j] = -1
            for q in range(used):
                gap = 0.0  # squared distance from the point to that cell's box
                for a in range(3):
                    off = offs[q, a]
                    if off < 0:
                        g = sorted_points[s, a] - box_lo[a]
                        gap += g * g
                    elif off > 0:
                        g = box_lo[a] + h - sorted_points[s, a]
                        gap += g * g
                if gap > best_d[k - 1]:
                    continue
                for u in range(first[q], last[q]):
                    ex, ey, ez = sorted_points[u, 0] - px, sorted_points[u, 1] - py, sorted_points[u, 2] - pz
                    d = ex * ex + ey * ey + ez * ez
                    if d < best_d[k - 1] and u != s:
                        _take(best_d, best_t, d, u)
            bound = np.inf
            for a in range(3):
                bound = min(bound, sorted_points[s, a] - bound_lo[a], bound_hi[a] - sorted_points[s, a])
            i = perm[s]
            certain[i] = best_t[k - 1] >= 0 and best_d[k - 1] < bound * bound
            for j in range(k):
                nb[i, j] = perm[best_t[j]] if best_t[j] >= 0 else -1


@kernel
def brute_neighbours(points, rows, k, lo, hi, nb):
    """nb[i] (k, indices into points) for i = rows[lo..hi-1]: the k nearest other points of point i
    by an exact sweep over every point (squared distances in float64; nearest first, ties: the
    lower index) -- for the few points whose grid cells cannot tell (`compiled.nearest`)."""
    best_d = np.empty(k)
    best_t = np.empty(k, np.int64)
    for r in range(lo, hi):
        i = rows[r]
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        for j in range(k):
            best_d[j] = np.inf
            best_t[j] = -1
        for u in range(points.shape[0]):
            ex, ey, ez = points[u, 0] - px, points[u, 1] - py, points[u, 2] - pz
            d = ex * ex + ey * ey + ez * ez
            if d < best_d[k - 1] and u != i:
                _take(best_d, best_t, d, u)
        for j in range(k):
            nb[i, j] = best_t[j]
