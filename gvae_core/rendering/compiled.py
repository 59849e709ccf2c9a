"""The renderer's compiled CPU path: `kernels` (Numba) driven from torch tensors.

What runs here: the projection (and its backward, `ProjectFunction`), tile binning, the
compositing (and its backward, through `rasterize.RasterizeFunction`) and the Gauss-Newton sweep
(each Gaussian's moments of its pixel derivatives and its blocks, what `gvae_core.hessian` scores),
for float32 tensors on the CPU. The torch code beside it (`projection`, `tiles`, `rasterize`) is
the reference these are tested against and what runs on a GPU, in float64 and with
`RenderSettings(kernels="torch")`.

Work is split into chunks (of Gaussians, of tiles) run in threads: the kernels release the GIL, so
there is no threading layer of Numba's, and nothing global is set; `parallel.count()` (torch's count)
threads, as the torch path uses. The first call of each kernel in a process loads it from the
on-disk cache (`kernels.kernel_cache_dir`, a user cache directory) or, the first time on a machine,
compiles it (`compile_kernels` does all of it at once and says so; `kernels.KERNELS` lists them).
Nothing here imports a module above the renderer (tests/test_layout.py).
"""

from __future__ import annotations

import importlib
import importlib.util
import threading
import time
from collections.abc import Callable

import numpy as np
import torch

from .. import quaternions
from ..camera import Camera
from ..parallel import chunks, count, run, split
from .projection import Projected, fov_limits
from .tiles import Binning

#: `RenderSettings.kernels` values: "auto" (compiled where it applies: float32 on the CPU, Numba
#: installed), "compiled" (the same, an error where it cannot), "torch" (the reference path).
KERNEL_CHOICES = ("auto", "compiled", "torch")
#: Pixel-Gaussian pairs (tile pairs x pixels) below which work is not split into threads.
_SMALL = 1 << 16
#: Tile pairs per chunk of the Hessian's sweep (bounds its per-chunk buffer: 136 bytes a pair).
_SWEEP_CHUNK = 1 << 15

def numba_missing() -> str | None:
    """Why the compiled path cannot run here (None when it can): Numba not installed, or not
    importable (for example a numpy outside the versions it supports); the torch code runs then."""
    if importlib.util.find_spec("numba") is None:
        return "Numba is not installed"
    try:
        importlib.import_module("numba")
    except Exception as exc:  # noqa: BLE001 - any failure to load it means: render with torch
        return f"Numba does not load here: {exc}"
    return None


def kernels():
    """The `kernels` module (imports Numba on first use, not when gvae_core is imported)."""
    return importlib.import_module(".kernels", __package__)


def use_compiled(choice: str, device, dtype) -> bool:
    """Whether the compiled path draws tensors of `device` and `dtype` under `RenderSettings.kernels`
    = choice (an error for "compiled" where it cannot)."""
    if choice not in KERNEL_CHOICES:
        raise ValueError(f"render: kernels must be one of {KERNEL_CHOICES}, got {choice!r}")
    if choice == "torch":
        return False
    why = numba_missing()
    if why is None and torch.device(device).type != "cpu":
        why = f"they run on the CPU, not on {device}"
    if why is None and dtype != torch.float32:
        why = f"they render in float32, not {dtype}"
    if why is not None and choice == "compiled":
        raise ValueError(f"render: the compiled kernels cannot be used: {why}")
    return why is None


# ------------------------------------------------------------------------------ threads

# ------------------------------------------------------------------------------ projection

def camera_vector(camera: Camera) -> np.ndarray:
    """The camera as the kernels read it (`kernels.CAM_SIZE` float64): world-to-camera rotation
    (row-major), centre, fx, fy, cx, cy, the Jacobian's clamp (`projection.fov_limits`) and the
    rotation as a quaternion (w, x, y, z)."""
    q = quaternions.from_rotmat(camera.rotation)
    return np.concatenate([np.asarray(camera.rotation, np.float64).reshape(-1), camera.center,
                           [camera.fx, camera.fy, camera.cx, camera.cy], fov_limits(camera), q]).astype(np.float64)


def _np(t, dtype) -> np.ndarray:
    t = t.detach().numpy() if isinstance(t, torch.Tensor) else t
    return np.ascontiguousarray(t, dtype=dtype)


class Inputs:
    """A cloud's fields as the kernels take them (numpy; positions float64, the rest float32), with
    the per-Gaussian 3D anti-aliasing size and `kernels` flags of its mode: made once, drawn through
    any number of cameras (`project_arrays`)."""

    def __init__(self, means, scales, quats, opacities, sh_dc, sh_rest, *, filter_3d=None, mip_2d: bool = False,
                 dilation_3d=None):
        k = kernels()
        if dilation_3d is not None and (filter_3d is not None or mip_2d):
            raise ValueError("project: dilation_3d does not go with the Mip filters")
        n = means.shape[0]
        self.means = _np(means, np.float64)
        self.scales, self.quats = _np(scales, np.float32), _np(quats, np.float32)
        self.logits = _np(opacities, np.float32).reshape(n)
        self.sh_dc = _np(sh_dc, np.float32)
        self.sh_rest = _np(sh_rest, np.float32).reshape(n, sh_rest.shape[1] if len(sh_rest.shape) == 3 else 0, 3)
        size = filter_3d if filter_3d is not None else dilation_3d
        self.sizes = _np(size, np.float32).reshape(n) if size is not None else np.zeros(0, np.float32)
        self.flags = ((k.FILTER_3D if filter_3d is not None else 0) | (k.DILATION_3D if dilation_3d is not None else 0)
                      | (k.MIP_2D if mip_2d else 0))

    def __len__(self) -> int:
        return self.means.shape[0]

    def fields(self):
        return self.means, self.scales, self.quats, self.logits, self.sh_dc, self.sh_rest, self.sizes


def project_arrays(inp: Inputs, camera: Camera, degree: int):
    """(table (N+1, 11) float32, footprint (N, 4) float64, radii (N,) int32, visible (N,) bool) of
    `inp` seen through `camera` (`kernels.project_forward`)."""
    k = kernels()
    n = len(inp)
    cam = camera_vector(camera)
    table = np.zeros((n + 1, 11), np.float32)
    foot = np.empty((n, 4), np.float64)
    radii = np.empty(n, np.int32)
    visible = np.empty(n, np.bool_)
    run([lambda a=a, b=b: k.project_forward(*inp.fields(), cam, int(degree), inp.flags, camera.width, camera.height,
                                             a, b, table, foot, radii, visible)
          for a, b in chunks(n, 64.0 * n, _SMALL)])
    return table, foot, radii, visible


class ProjectFunction(torch.autograd.Function):
    """Raw parameters (6 tensors) -> the packed table (N+1, 11) that `project_arrays` made of them,
    with the compiled backward (`kernels.project_backward`)."""

    @staticmethod
    def forward(ctx, means, scales, quats, opacities, sh_dc, sh_rest, inp: Inputs, camera: Camera, degree: int,
                table: np.ndarray):
        ctx.inp, ctx.camera, ctx.degree, ctx.table = inp, camera, degree, table
        ctx.like = [(t.shape, t.dtype) for t in (means, scales, quats, opacities, sh_dc, sh_rest)]
        return torch.from_numpy(table)

    @staticmethod
    def backward(ctx, grad_table):
        k = kernels()
        inp = ctx.inp
        n = len(inp)
        cam = camera_vector(ctx.camera)
        g = np.ascontiguousarray(grad_table.numpy(), np.float32)
        out = [np.empty((n, 3), np.float64), np.empty((n, 3), np.float32), np.empty((n, 4), np.float32),
               np.empty(n, np.float32), np.empty((n, 3), np.float32), np.empty(inp.sh_rest.shape, np.float32)]
        run([lambda a=a, b=b: k.project_backward(*inp.fields(), cam, int(ctx.degree), inp.flags, a, b, ctx.table, g,
                                                  *out)
              for a, b in chunks(n, 64.0 * n, _SMALL)])
        grads = [torch.from_numpy(o).reshape(shape).to(dtype) for o, (shape, dtype) in zip(out, ctx.like)]
        return (*grads, None, None, None, None)


def project(means, scales, quats, opacities, sh_dc, sh_rest, camera: Camera, degree: int, *, filter_3d=None,
            mip_2d: bool = False, dilation_3d=None) -> tuple[Projected, torch.Tensor]:
    """`projection.project` (same arguments, float32) by the kernels: (Projected, the packed table
    (N+1, 11) of `rasterize.pack`). The Projected fields are views of the table; with gradients
    enabled and some input requiring them, the table is the output of `ProjectFunction`."""
    inp = Inputs(means, scales, quats, opacities, sh_dc, sh_rest, filter_3d=filter_3d, mip_2d=mip_2d,
                 dilation_3d=dilation_3d)
    table_np, foot, radii, visible = project_arrays(inp, camera, degree)
    fields = (means, scales, quats, opacities, sh_dc, sh_rest)
    if torch.is_grad_enabled() and any(t.requires_grad for t in fields):
        table = ProjectFunction.apply(*fields, inp, camera, degree, table_np)
    else:
        table = torch.from_numpy(table_np)
    return projected(table, foot, radii, visible), table


def projected(table: torch.Tensor, foot: np.ndarray, radii: np.ndarray, visible: np.ndarray) -> Projected:
    """The `Projected` of a packed table (its fields are views of the table) and the rest."""
    rows = table[:-1]
    return Projected(means2d=rows[:, 0:2], conics=rows[:, 2:5], opacities=rows[:, 5], colors=rows[:, 6:9],
                     depths=rows[:, 9], radii=torch.from_numpy(radii), visible=torch.from_numpy(visible),
                     footprint=torch.from_numpy(foot))


# ------------------------------------------------------------------------------ binning

def bin_gaussians(table: torch.Tensor, footprint: torch.Tensor, visible: torch.Tensor, width: int, height: int,
                  tile_size: int, exact: bool = True) -> Binning:
    """`tiles.bin_gaussians` of a projected table (the same pairs in the same order)."""
    k = kernels()
    ts = tile_size
    tiles_x, tiles_y = (width + ts - 1) // ts, (height + ts - 1) // ts
    ntiles = tiles_x * tiles_y
    tab = table.detach().numpy()
    foot = footprint.numpy()
    order = np.flatnonzero(visible.numpy()).astype(np.int64)
    keys = np.ascontiguousarray(tab[order, k.DEPTH]).view(np.uint32)  # positive depths: their bits sort alike
    k.radix_order(keys, order)
    parts = chunks(len(order), 16.0 * len(order), _SMALL)
    geo = np.empty((len(order), k.GEO), np.float64)
    run([lambda a=a, b=b: k.gather_footprints(tab, foot, order, a, b, geo) for a, b in parts])
    hist = np.zeros((max(len(parts), 1), ntiles), np.int64)
    run([lambda c=c, a=a, b=b: k.bin_count(geo, a, b, ts, tiles_x, width, height, exact, hist[c])
          for c, (a, b) in enumerate(parts)])
    counts = hist.sum(0)
    offsets = np.zeros(ntiles + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    cursor = offsets[:-1] + np.cumsum(hist, 0) - hist  # each chunk's first place in every tile's list
    ids = np.empty(int(offsets[-1]), np.int64)
    run([lambda c=c, a=a, b=b: k.bin_fill(geo, order, a, b, ts, tiles_x, width, height, exact, cursor[c], ids)
          for c, (a, b) in enumerate(parts)])
    return Binning(ts, tiles_x, tiles_y, torch.from_numpy(ids), torch.from_numpy(offsets), torch.from_numpy(counts))


# ------------------------------------------------------------------------------ compositing

def _tile_chunks(binning: Binning) -> list[tuple[int, int]]:
    """Ranges of tiles of about equal work (their pairs, plus a little per tile)."""
    counts = binning.counts.numpy()
    p = binning.tile_size ** 2
    work = float(counts.sum()) * p
    parts = 1 if work < _SMALL or count() == 1 else 8 * count()
    return split(counts + 1.0, parts)


def _arrays(table: torch.Tensor, binning: Binning):
    return (np.ascontiguousarray(table.detach().numpy(), np.float32), binning.gaussian_ids.numpy(),
            binning.offsets.numpy())


def composite_forward(table: torch.Tensor, binning: Binning) -> torch.Tensor:
    """`rasterize.composite` without gradients: (tiles, 5, P) float32; sets binning.evaluations."""
    k = kernels()
    tab, ids, offsets = _arrays(table, binning)
    p = binning.tile_size ** 2
    acc = np.empty((binning.tiles_x * binning.tiles_y, 5, p), np.float32)
    evals = run([lambda a=a, b=b: k.composite_forward(tab, ids, offsets, a, b, binning.tiles_x, binning.tile_size,
                                                       acc)
                  for a, b in _tile_chunks(binning)])
    binning.evaluations = int(sum(evals))
    return torch.from_numpy(acc)


def composite_backward(table: torch.Tensor, binning: Binning, acc: torch.Tensor,
                       grad_acc: torch.Tensor) -> torch.Tensor:
    """d loss / d table (N+1, 11) from d loss / d acc (tiles, 5, P) (`rasterize.RasterizeFunction`'s
    backward; columns past the 10th and the dummy row get no gradient but the opacity rule's 0)."""
    k = kernels()
    tab, ids, offsets = _arrays(table, binning)
    acc_np = np.ascontiguousarray(acc.numpy(), np.float32)
    g = np.ascontiguousarray(grad_acc.numpy(), np.float32)
    pair_grads = np.zeros((len(ids), k.NGRAD), np.float32)
    run([lambda a=a, b=b: k.composite_backward(tab, ids, offsets, a, b, binning.tiles_x, binning.tile_size, acc_np,
                                                g, pair_grads)
          for a, b in _tile_chunks(binning)])
    grad_table = np.zeros(tab.shape, np.float32)
    parts = 1 if len(ids) * k.NGRAD < _SMALL else min(count(), k.NGRAD)
    run([lambda a=a, b=b: k.pair_grads_to_table(pair_grads, ids, tab, a, b, grad_table)
          for a, b in split(np.ones(k.NGRAD), parts)])
    return torch.from_numpy(grad_table)


def _tile_ranges(binning: Binning) -> list[tuple[int, int]]:
    """Ranges of tiles of equal size for a pass over every pixel."""
    ntiles = binning.tiles_x * binning.tiles_y
    return chunks(ntiles, float(ntiles * binning.tile_size ** 2), _SMALL)


class AssembleFunction(torch.autograd.Function):
    """acc (tiles, 5, P) -> (image (H, W, 3), alpha (H, W), depth (H, W)) over `background`, with
    the compiled backward: `render`'s last step in one pass each way (`kernels.assemble_forward`)."""

    @staticmethod
    def forward(ctx, acc, binning: Binning, height: int, width: int, background: np.ndarray):
        k = kernels()
        acc_np = acc.detach().numpy()
        image, alpha, depth = (np.empty((height, width, 3), np.float32), np.empty((height, width), np.float32),
                               np.empty((height, width), np.float32))
        run([lambda a=a, b=b: k.assemble_forward(acc_np, binning.tiles_x, binning.tile_size, background, a, b, image,
                                                  alpha, depth)
              for a, b in _tile_ranges(binning)])
        ctx.save_for_backward(acc)
        ctx.set_materialize_grads(False)
        ctx.binning, ctx.background, ctx.size = binning, background, (height, width)
        return torch.from_numpy(image), torch.from_numpy(alpha), torch.from_numpy(depth)

    @staticmethod
    def backward(ctx, g_image, g_alpha, g_depth):
        k = kernels()
        (acc,) = ctx.saved_tensors
        binning = ctx.binning
        acc_np = acc.numpy()
        h, w = ctx.size
        none = np.zeros((0, 0), np.float32)
        gi = np.zeros((h, w, 3), np.float32) if g_image is None else np.ascontiguousarray(g_image.numpy(), np.float32)
        ga, gd = (none if g is None else np.ascontiguousarray(g.numpy(), np.float32) for g in (g_alpha, g_depth))
        g_acc = np.empty(acc_np.shape, np.float32)
        run([lambda a=a, b=b: k.assemble_backward(acc_np, binning.tiles_x, binning.tile_size, ctx.background, a, b, h,
                                                   w, gi, ga, gd, g_acc)
              for a, b in _tile_ranges(binning)])
        return torch.from_numpy(g_acc), None, None, None, None


def assemble(acc: torch.Tensor, binning: Binning, height: int, width: int,
             background) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(image, alpha, depth) of the compositing's acc (tiles, 5, P) float32 over `background` (3
    floats), as `render` makes them with torch (`rasterize.tiles_to_image`, then the background and
    the depth's division), in one compiled pass; differentiable in acc."""
    bg = np.ascontiguousarray(np.asarray(background, np.float32).reshape(3))
    return AssembleFunction.apply(acc.contiguous(), binning, height, width, bg)


# ------------------------------------------------------------------------------ the Gauss-Newton sweep

def gauss_newton_moments(table: torch.Tensor, binning: Binning, acc: torch.Tensor, width: int, height: int,
                         out: np.ndarray) -> None:
    """Add each Gaussian's moments of its pixel derivatives (`kernels.gauss_newton_moments`) into
    out (N, 34) float32 (`hessian._gauss_newton_sweep` by the kernels).

    The tiles are swept in chunks (one moment buffer each) in the threads; each chunk's moments are
    added into `out` one stripe of Gaussians at a time, and every stripe takes the chunks in their
    order: threads add into different stripes at once, and each Gaussian's sum is made in the same
    order whatever the threads (the same figures as one thread, run after run)."""
    k = kernels()
    tab, ids, offsets = _arrays(table, binning)
    acc_np = np.ascontiguousarray(acc.numpy(), np.float32)
    counts = binning.counts.numpy()
    # ranges of tiles of at most about _SWEEP_CHUNK pairs (one buffer each), in the threads
    chunk = max(_SWEEP_CHUNK, int(counts.max(initial=0)))
    ranges = split(counts + 1.0, max(1, -(-int(counts.sum()) // chunk)))
    stripes = split(np.ones(len(out)), count()) or [(0, 0)]
    turn = [0] * len(stripes)  # the chunk each stripe takes its adds from next
    failed = []  # a chunk that raised: the later ones stop waiting for it
    changed = threading.Condition()

    def sweep(c: int, a: int, b: int) -> None:
        try:
            base, stop = int(offsets[a]), int(offsets[b])
            moments = np.zeros((stop - base, k.NMOM), np.float32)
            k.gauss_newton_moments(tab, ids, offsets, a, b, binning.tiles_x, binning.tile_size, width, height,
                                   acc_np, moments, base)
            for s in [(c + j) % len(stripes) for j in range(len(stripes))]:  # threads start on different stripes
                with changed:
                    changed.wait_for(lambda s=s: turn[s] == c or failed)
                if failed:
                    return
                k.add_moments(moments, ids, base, stripes[s][0], stripes[s][1], out)  # stripe s is this chunk's
                with changed:
                    turn[s] += 1
                    changed.notify_all()
        except BaseException:
            with changed:
                failed.append(c)
                changed.notify_all()
            raise

    run([lambda c=c, a=a, b=b: sweep(c, a, b) for c, (a, b) in enumerate(ranges)])


def gaussian_blocks(inp: Inputs, camera: Camera, degree: int, scale: float, table: torch.Tensor,
                    moments: np.ndarray, out: np.ndarray) -> None:
    """out (N, 21) float64 += this view's packed Gauss-Newton blocks of every Gaussian with some
    weight in `moments` (N, 34) (`kernels.gaussian_blocks`; `hessian._gaussian_blocks` by the kernels);
    `moments` is all zeros afterwards (what the next view's sweep adds into)."""
    k = kernels()
    n = len(inp)
    cam = camera_vector(camera)
    tab = np.ascontiguousarray(table.detach().numpy(), np.float32)
    run([lambda a=a, b=b: k.gaussian_blocks(inp.means, inp.scales, inp.quats, inp.sh_rest, inp.sizes, cam,
                                             int(degree), inp.flags, float(scale), tab, moments, a, b, out)
          for a, b in chunks(n, 64.0 * n, _SMALL)])


def logdet_scores(rows: np.ndarray, lam: float) -> np.ndarray:
    """(N,) float32 log det(I + H / lam) of the blocks whose packed upper triangles are rows (N, 21)
    float64 (`kernels.logdet_scores`; `hessian.scores_from_packed`'s log-determinant by the kernels)."""
    k = kernels()
    n = rows.shape[0]
    out = np.empty(n, np.float32)
    rows = np.ascontiguousarray(rows, np.float64)
    run([lambda a=a, b=b: k.logdet_scores(rows, float(lam), a, b, out) for a, b in chunks(n, 256.0 * n, _SMALL)])
    return out


# ------------------------------------------------------------------------------ compiling

def kernels_cached() -> bool:
    """Whether every kernel is in the on-disk cache for this Numba and this version of the kernels
    (then the first render of a process only loads them)."""
    k = kernels()
    return all(k.is_cached(getattr(k, name)) for name in k.KERNELS)


def compile_kernels(progress: Callable[[float, str], None] | None = None) -> float:
    """Make every kernel (`kernels.KERNELS`) ready in this process: loaded from the on-disk cache, or
    compiled where it is not there (the first run on a machine or after an update). Calls
    progress(0, message) first when something must be compiled. Returns the seconds it took.

    A tiny scene goes once through each step of this module, forward and backward, with the argument
    types that `render` and the Gauss-Newton sweep give the kernels (one set each: tests/test_kernels.py
    holds them to it), so that what is made ready here is what they run."""
    t0 = time.perf_counter()
    if progress is not None and not kernels_cached():
        progress(0.0, "Compiling the renderer's CPU kernels (first run only, up to a minute)")
    n, degree = 8, 3
    rng = np.random.default_rng(0)
    fields = (torch.tensor(rng.normal(0, 0.3, (n, 3)), dtype=torch.float32, requires_grad=True),
              torch.full((n, 3), -2.0), torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32), torch.zeros(n),
              torch.zeros((n, 3)), torch.zeros((n, 15, 3)))
    cam = Camera.look_at((2.0, 0.5, 1.0), width=8, height=8)
    proj, table = project(*fields, cam, degree)
    binning = bin_gaussians(table, proj.footprint, proj.visible, cam.width, cam.height, tile_size=4)
    acc = composite_forward(table, binning)
    # (a scalar's backward: torch imports sympy, a second, for a backward given its gradient)
    (table * composite_backward(table, binning, acc, torch.ones_like(acc))).sum().backward()
    image, alpha, depth = assemble(acc.detach().clone().requires_grad_(), binning, cam.height, cam.width,
                                   (0.0, 0.0, 0.0))
    (image.sum() + alpha.sum() + depth.sum()).backward()
    moments = np.zeros((n, kernels().NMOM), np.float32)
    gauss_newton_moments(table, binning, acc, cam.width, cam.height, moments)
    blocks = np.zeros((n, 21), np.float64)  # a packed 6x6 block each
    gaussian_blocks(Inputs(*fields), cam, degree, 1.0, table, moments, blocks)
    logdet_scores(blocks, 1.0)
    return time.perf_counter() - t0


def main() -> None:
    """Make the kernels ready and say where they are kept (`make test` runs this first)."""
    if numba_missing():
        print(f"compiled kernels: {numba_missing()}; the torch code renders")
        return
    seconds = compile_kernels(lambda _, message: print(message, flush=True))
    print(f"compiled kernels ready in {seconds:.1f} s ({kernels().kernel_cache_dir()})")
