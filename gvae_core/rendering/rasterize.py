"""Rasterisation stage: front-to-back alpha compositing of depth-sorted per-tile lists.

Tiles with similar list lengths are processed together in dense blocks laid out list-major,
(Gaussians k, tiles b, pixels p), which makes every step a fast tensor op on CPU:
- the Gaussian exponent of every pixel-Gaussian pair is one GEMM: per pair, 6 coefficients of
  a quadratic in tile-local pixel coordinates (log-opacity folded into the constant), times the
  fixed (6, P) table of pixel monomials;
- alpha = exp, capped at 0.99, zeroed below 1/255 (in-place clamp and threshold);
- transmittance by a running product over k (contiguous (tiles, pixels) slabs);
- the stop rule without masks: T kept where >= 1e-4, else replaced by 2, so the weight
  w = max(T_before - T_after, 0) vanishes from the stopping Gaussian on;
- accumulation of [r, g, b, depth, 1] weighted by w is one batched GEMM.
Transmittance and "stopped" flags carry from block to block; tiles that are finished (all
pixels stopped, or lists exhausted) drop out (early termination).

`RasterizeFunction` wraps this in a custom autograd Function whose backward recomputes each
block (nothing of size pixels x Gaussians is stored), so memory stays bounded by the block
budget. On the CPU in float32 the same Function runs the compiled kernels instead
(`compiled.composite_forward` / `composite_backward`: tile by tile, pixel by pixel), which this
code is the reference for. `differentiable_composite` is an independent formulation with plain autograd ops
(it stores everything): a cross-check for the hand-written backward and a fallback.

Other sweeps over the tile lists recompute the compositing with its steps, which are public for
them (the Hessian's Gauss-Newton sweep, compaction's scoring): `tile_groups`, `pair_table`,
`live_blocks` (the blocks front to back), `pixel_monomials`, `tile_centres`,
`alpha_and_transmittance` and `compositing_weights` (every rule above, the cap, skip and stop).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from . import compiled as _compiled
from .tiles import Binning

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
#: Columns of the packed per-Gaussian table.
MX, MY, CA, CB, CC, OP = range(6)
FEAT = slice(6, 11)  # r, g, b, depth, 1: what each pixel accumulates with weight alpha * T
NCOL = 11
NFEAT = 5


def _below(x: float, dtype) -> float:
    """The largest value of `dtype` below x: `threshold(t, _below(x), v)` keeps t >= x."""
    t = torch.tensor(x, dtype=dtype)
    return float(torch.nextafter(t, torch.zeros_like(t)))


def pack(means2d, conics, opacities, colors, depths) -> torch.Tensor:
    """The (N+1, 11) per-Gaussian table; the last row is a transparent dummy used as padding."""
    n = means2d.shape[0]
    ones = torch.ones((n, 1), dtype=means2d.dtype, device=means2d.device)
    table = torch.cat([means2d, conics, opacities[:, None], colors, depths[:, None], ones], 1)
    dummy = torch.zeros((1, NCOL), dtype=table.dtype, device=table.device)
    return torch.cat([table, dummy], 0)


def tile_groups(binning: Binning, block: int, budget: int) -> list[tuple[torch.Tensor, int]]:
    """Non-empty tiles, longest lists first, in groups of about `budget` pair evaluations per block."""
    counts = binning.counts
    order = torch.sort(counts, descending=True, stable=True).indices
    nonempty = int((counts > 0).sum())
    order = order[:nonempty]
    sorted_counts = counts[order].tolist()
    p = binning.tile_size ** 2
    groups = []
    i = 0
    while i < nonempty:
        kmax = sorted_counts[i]
        b = max(1, budget // (p * min(kmax, block)))
        groups.append((order[i:i + b], kmax))
        i += b
    return groups


def pixel_monomials(ts: int, dtype, device) -> torch.Tensor:
    """(6, P): 1, u, v, u², uv, v² of each pixel centre relative to its tile's centre."""
    r = torch.arange(ts, dtype=dtype, device=device) - (ts - 1) / 2.0
    u = r.repeat(ts)
    v = r.repeat_interleave(ts)
    return torch.stack([torch.ones_like(u), u, v, u * u, u * v, v * v], 0)


def tile_centres(tiles, binning: Binning, dtype):
    """(cx, cy): the pixel coordinates of the centres of `tiles` (indices, row-major), in `dtype`."""
    ts = binning.tile_size
    cx = (tiles % binning.tiles_x).to(dtype) * ts + ts / 2.0
    cy = (tiles // binning.tiles_x).to(dtype) * ts + ts / 2.0
    return cx, cy


def _block_pairs(start, count, k0, kb, dummy):
    """(kb, B) pair indices of list positions k0..k0+kb of each tile (`dummy` past the end)."""
    kk = torch.arange(k0, k0 + kb, device=start.device)
    pos = start[None, :] + kk[:, None]
    return torch.where(kk[:, None] < count[None, :], pos, torch.full_like(pos, dummy))


def live_blocks(start, count, done, kmax: int, block: int, dummy: int):
    """The blocks of list positions a group of tiles composites, front to back: (active tiles,
    k0, kb, pair indices (kb, B_active)). Tiles drop out once their lists end or all their pixels
    have stopped; `done` (B, P) is read as the caller updates it in place."""
    active = torch.arange(start.shape[0], device=start.device)
    for k0 in range(0, kmax, block):
        alive = (count[active] > k0) & ~done[active].all(1)
        if not bool(alive.all()):
            active = active[alive]
            if active.numel() == 0:
                return
        kb = min(block, kmax - k0)
        yield active, k0, kb, _block_pairs(start[active], count[active], k0, kb, dummy)


def pair_table(table: torch.Tensor, binning: Binning) -> torch.Tensor:
    """(M+1, 11): the table row of each tile-Gaussian pair in list order, then the dummy row."""
    out = torch.empty((binning.num_pairs + 1, table.shape[1]), dtype=table.dtype, device=table.device)
    torch.index_select(table, 0, binning.gaussian_ids, out=out[:-1])
    out[-1] = table[-1]
    return out


def alpha_and_transmittance(gd, cx, cy, mono, t0):
    """One block of the compositing of B tiles: from the pairs' table rows gd (kb,B,11) (`pair_table`
    rows at `live_blocks`' indices), the tiles' centres cx, cy (B,) (`tile_centres`), the pixel
    monomials (6,P) (`pixel_monomials`) and the transmittance t0 (B,P) before the block: alpha
    (kb,B,P) (capped at ALPHA_MAX, 0 below ALPHA_MIN), transmittance T (kb+1,B,P) with T[0] = t0,
    and the quadratic's per-pair offsets mu, mv (kb,B) of the Gaussian centre from the tile centre."""
    kb, b = gd.shape[:2]
    p = mono.shape[1]
    mu = gd[..., MX] - cx
    mv = gd[..., MY] - cy
    a, bb, c = gd[..., CA], gd[..., CB], gd[..., CC]
    c0 = torch.log(gd[..., OP]) - 0.5 * a * mu * mu - bb * mu * mv - 0.5 * c * mv * mv
    coef = torch.stack([c0, a * mu + bb * mv, bb * mu + c * mv, -0.5 * a, -bb, -0.5 * c], -1)
    alpha = torch.mm(coef.reshape(kb * b, 6), mono).reshape(kb, b, p)
    alpha.exp_().clamp_(max=ALPHA_MAX)
    F.threshold_(alpha, _below(ALPHA_MIN, alpha.dtype), 0.0)
    trans = torch.empty((kb + 1, b, p), dtype=gd.dtype, device=gd.device)
    trans[0] = t0
    for k in range(kb):  # T_{k+1} = T_k - T_k alpha_k
        torch.addcmul(trans[k], trans[k], alpha[k], value=-1.0, out=trans[k + 1])
    return alpha, trans, mu, mv


def compositing_weights(trans):
    """The stop rule on a block's transmittance T (kb+1,B,P) (`alpha_and_transmittance`): w (kb,B,P)
    = alpha*T of the kept contributions (0 from the Gaussian that would take T below T_MIN on), and
    T_kept = T after each, or 2 past the stop."""
    kept = F.threshold(trans[1:], _below(T_MIN, trans.dtype), 2.0)
    return torch.sub(trans[:-1], kept).clamp_(min=0.0), kept


def _run_group(pairs, binning, tiles, kmax, block, gvec=None, grad_pairs=None, acc_fwd=None):
    """Forward (gvec None): (accumulated features (B,5,P) of `tiles`, evaluations), from the
    pair table `pairs` (M+1, 11). Backward: the same recomputation, writing d loss / d pair row
    into `grad_pairs` (with d loss / d log opacity in the opacity column) for the gradient
    `gvec` (B,5,P) of the accumulated features, whose forward values are `acc_fwd` (B,5,P)."""
    dummy = pairs.shape[0] - 1
    table = pairs
    dt, dev = table.dtype, table.device
    ts = binning.tile_size
    mono = pixel_monomials(ts, dt, dev)
    p = ts * ts
    b = tiles.shape[0]
    cx_all, cy_all = tile_centres(tiles, binning, dt)
    start = binning.offsets[tiles]
    count = binning.counts[tiles]
    trans = torch.ones((b, p), dtype=dt, device=dev)
    done = torch.zeros((b, p), dtype=torch.bool, device=dev)
    forward = gvec is None
    acc = torch.zeros((b, NFEAT, p), dtype=dt, device=dev) if forward else None
    if not forward:
        rest = (gvec * acc_fwd).sum(1)  # Σ_j v_j w_j over the whole list: what lies behind
    evaluations = 0
    for active, k0, kb, ids in live_blocks(start, count, done, kmax, block, dummy):
        gd = table.index_select(0, ids.reshape(-1)).reshape(kb, -1, NCOL)  # (kb, B, 11)
        evaluations += ids.numel() * p
        was_done = done[active]
        t_prev = trans[active]
        t0 = torch.where(was_done, torch.zeros_like(t_prev), t_prev)
        alpha, tr, mu, mv = alpha_and_transmittance(gd, cx_all[active], cy_all[active], mono, t0)
        w, kept = compositing_weights(tr)
        if k0 + block < kmax:  # carried to the next block
            trans[active] = torch.where(was_done, t_prev, torch.minimum(t0, kept.amin(0)))
            done[active] = was_done | (tr[-1] < T_MIN)
        feat = gd[..., FEAT]  # (kb,B,5)
        if forward:
            acc[active] += torch.bmm(feat.permute(1, 2, 0), w.permute(1, 0, 2))
            continue
        gv = gvec[active]
        v = torch.bmm(feat.transpose(0, 1), gv).transpose(0, 1)  # (kb,B,P) view: feat·gvec
        behind = v * w  # becomes Σ_{j>k} v_j w_j in place below
        r = rest[active]
        for k in range(kb):
            torch.sub(r if k == 0 else behind[k - 1], behind[k], out=behind[k])
        rest[active] = behind[-1]
        # d loss / d alpha_k = v_k T_k - behind_k / (1 - alpha_k); times alpha = d / d exponent,
        # which is 0 where alpha is capped, skipped (alpha = 0) or past the stop (w = 0).
        # (Masks as arithmetic: threshold(-alpha) is -alpha below the cap, else 0; sign(w) is 1
        # for kept contributions, else 0; both far cheaper than boolean masks on CPU.)
        g = behind.div_(torch.rsub(alpha, 1.0)).sub_(v * tr[:-1])  # = -d loss / d alpha
        g.mul_(F.threshold(alpha.neg_(), -ALPHA_MAX, 0.0)).mul_(torch.sign(w))
        gc = torch.mm(g.reshape(-1, p), mono.T).reshape(kb, -1, 6)  # d loss / d coefficients
        g0, g1, g2, g3, g4, g5 = gc.unbind(-1)
        a, bb, c = gd[..., CA], gd[..., CB], gd[..., CC]
        grads = torch.empty(gd.shape, dtype=dt, device=dev)
        grads[..., MX] = g0 * (-a * mu - bb * mv) + g1 * a + g2 * bb
        grads[..., MY] = g0 * (-bb * mu - c * mv) + g1 * bb + g2 * c
        grads[..., CA] = -0.5 * (g0 * mu * mu - 2.0 * g1 * mu + g3)
        grads[..., CB] = -g0 * mu * mv + g1 * mv + g2 * mu - g4
        grads[..., CC] = -0.5 * (g0 * mv * mv - 2.0 * g2 * mv + g5)
        grads[..., OP] = g0
        grads[..., FEAT] = torch.bmm(gv, w.permute(1, 2, 0)).permute(2, 0, 1)
        grad_pairs.index_copy_(0, ids.reshape(-1), grads.reshape(-1, NCOL))  # each pair once
    return acc, evaluations


class RasterizeFunction(torch.autograd.Function):
    """table (N+1,11) -> accumulated features (tiles, 5, P) with a recomputing backward (the
    compiled kernels' when `compiled`, else the torch blocks')."""

    @staticmethod
    def forward(ctx, table, binning: Binning, block: int, budget: int, compiled: bool = False):
        if compiled:
            acc = _compiled.composite_forward(table, binning)
        else:
            acc = _forward_all(table, binning, block, budget)
        ctx.binning, ctx.block, ctx.budget, ctx.compiled = binning, block, budget, compiled
        ctx.save_for_backward(table, acc)
        return acc

    @staticmethod
    def backward(ctx, g_acc):
        table, acc = ctx.saved_tensors
        binning = ctx.binning
        if ctx.compiled:
            return _compiled.composite_backward(table, binning, acc, g_acc), None, None, None, None
        with torch.no_grad():
            pairs = pair_table(table, binning)
            grad_pairs = torch.zeros_like(pairs)
            for tiles, kmax in tile_groups(binning, ctx.block, ctx.budget):
                _run_group(pairs, binning, tiles, kmax, ctx.block, gvec=g_acc[tiles].contiguous(),
                           grad_pairs=grad_pairs, acc_fwd=acc[tiles])
            grad_table = torch.zeros_like(table)
            grad_table.index_add_(0, binning.gaussian_ids, grad_pairs[:-1])
            o = table[:, OP]
            grad_table[:, OP] = torch.where(o > 0, grad_table[:, OP] / torch.where(o > 0, o, torch.ones_like(o)),
                                            torch.zeros_like(o))
        return grad_table, None, None, None, None


def _forward_all(table, binning: Binning, block: int, budget: int, pairs=None) -> torch.Tensor:
    ntiles = binning.tiles_x * binning.tiles_y
    p = binning.tile_size ** 2
    acc = torch.zeros((ntiles, NFEAT, p), dtype=table.dtype, device=table.device)
    evaluations = 0
    with torch.no_grad():
        pairs = pair_table(table.detach(), binning) if pairs is None else pairs
        for tiles, kmax in tile_groups(binning, block, budget):
            acc[tiles], ev = _run_group(pairs, binning, tiles, kmax, block)
            evaluations += ev
    binning.evaluations = evaluations
    return acc


def differentiable_composite(table, binning: Binning, block: int, budget: int) -> torch.Tensor:
    """The same accumulated features (tiles, 5, P) with plain autograd ops, written directly
    from the per-pixel rules (pixel offsets, conic, cumprod, mask); stores everything."""
    ntiles = binning.tiles_x * binning.tiles_y
    ts = binning.tile_size
    p = ts * ts
    dummy = table.shape[0] - 1
    local = torch.arange(p, device=table.device)
    parts, where = [], []
    for tiles, kmax in tile_groups(binning, block, budget):
        px = ((tiles % binning.tiles_x)[:, None] * ts + (local % ts)[None, :]).to(table.dtype) + 0.5
        py = ((tiles // binning.tiles_x)[:, None] * ts + (local // ts)[None, :]).to(table.dtype) + 0.5
        pos = _block_pairs(binning.offsets[tiles], binning.counts[tiles], 0, kmax, binning.num_pairs).T
        ids = torch.cat([binning.gaussian_ids, binning.gaussian_ids.new_tensor([dummy])])[pos]
        gd = table[ids]  # (B,K,11)
        dx = px[:, :, None] - gd[:, None, :, MX]
        dy = py[:, :, None] - gd[:, None, :, MY]
        power = (-0.5 * (gd[:, None, :, CA] * dx * dx + gd[:, None, :, CC] * dy * dy)
                 - gd[:, None, :, CB] * dx * dy)
        alpha = (gd[:, None, :, OP] * torch.exp(power)).clamp(max=ALPHA_MAX)
        alpha = torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha))
        t_after = torch.cumprod(1.0 - alpha, -1)
        keep = (t_after >= T_MIN).detach()
        t_before = torch.cat([torch.ones_like(t_after[:, :, :1]), t_after[:, :, :-1]], -1)
        w = alpha * t_before * keep
        parts.append(torch.bmm(w, gd[:, :, FEAT]).transpose(1, 2))
        where.append(tiles)
        binning.evaluations += ids.numel() * p
    acc = torch.zeros((ntiles, NFEAT, p), dtype=table.dtype, device=table.device)
    if parts:
        acc = acc.index_put((torch.cat(where),), torch.cat(parts))
    return acc


def composite(table, binning: Binning, *, block: int = 64, budget: int = 1 << 21,
              backward: str = "recompute", pairs: torch.Tensor | None = None, kernels: str = "auto") -> torch.Tensor:
    """Accumulated features (tiles, 5, P) = Σ w·[r, g, b, depth, 1] per pixel, in tile layout.
    `pairs`: `pair_table(table, binning)` when the caller made it already (used without autograd);
    `kernels`: `RenderSettings.kernels` (the compiled kernels or this module's torch code)."""
    if backward not in ("recompute", "autograd"):
        raise ValueError(f"backward must be 'recompute' or 'autograd', got {backward!r}")
    binning.evaluations = 0
    grad = table.requires_grad and torch.is_grad_enabled()
    if backward == "autograd" and grad:
        return differentiable_composite(table, binning, block, budget)
    fast = _compiled.use_compiled(kernels, table.device, table.dtype)
    if grad:
        return RasterizeFunction.apply(table, binning, block, budget, fast)
    if fast:
        return _compiled.composite_forward(table, binning)
    return _forward_all(table, binning, block, budget, pairs)


def tiles_to_image(acc: torch.Tensor, binning: Binning, height: int, width: int) -> torch.Tensor:
    """(tiles, C, P) tile layout to a (H, W, C) image (cropping the padded border tiles)."""
    ts = binning.tile_size
    c = acc.shape[1]
    img = acc.reshape(binning.tiles_y, binning.tiles_x, c, ts, ts).permute(0, 3, 1, 4, 2)
    return img.reshape(binning.tiles_y * ts, binning.tiles_x * ts, c)[:height, :width]
