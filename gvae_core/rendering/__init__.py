"""Differentiable tile-based 3D Gaussian splatting on PyTorch (CPU or any torch device).

`render(cloud, camera)` follows "Rendering semantics" in DESIGN.md; `reference.render_reference`
is the slow float64 per-pixel loop it is tested against. Stages: `projection` (per Gaussian;
positions relative to the camera in float64, the rest in the working dtype), `tiles` (exact
footprint-tile binning, depth order), `rasterize` (blocked compositing, recomputing backward;
its steps are public for the sweeps that recompute it: the Hessian's, compaction's scoring);
`frames` keeps a view's table and tile lists to redraw it after a few Gaussians changed.
On the CPU in float32 the stages run as compiled kernels (`compiled`, `kernels`: Numba), which
the torch code is the reference for; `RenderSettings.kernels` chooses; `compiled.compile_kernels`
makes them all ready at once. The renderer imports nothing above it (tests/test_layout.py).

On a machine shared with other work, run with OMP_WAIT_POLICY=PASSIVE in the environment (set
before torch is imported): spinning OpenMP threads otherwise stall each other (measured 20x).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..antialias import ANTIALIAS_MODES, DEFAULT_ANTIALIAS, DILATION_KEY, FILTER_KEY, resolve_antialias
from ..camera import Camera
from ..cloud import GaussianCloud
from ..conventions import is_torch
from ..octaves import SIZE, drawn_fields
from . import compiled
from .projection import Projected, project
from .rasterize import composite, pack, tiles_to_image
from .tiles import Binning, bin_gaussians

__all__ = ["render", "project_view", "prepare_view", "RenderOutput", "RenderSettings", "ANTIALIAS_MODES",
           "antialias_parts", "resolve_device"]


@dataclass
class RenderSettings:
    """How to render: the anti-aliasing mode, and knobs of the fast path that never change the
    image (beyond float32 rounding).

    antialias: one of `gvae_core.antialias.ANTIALIAS_MODES` (what they mean is said there);
    tile_size: tile edge in pixels; block: Gaussians per compositing block; budget: pixel-Gaussian
    pairs evaluated at once (bounds memory: about 40 bytes each); backward: "recompute" (custom
    autograd Function, bounded memory) or "autograd" (plain PyTorch ops, stores everything);
    exact_tiles: drop tile pairs the footprint ellipse misses (not just its bounding box);
    dtype: rasteriser precision (float64 for gradcheck); kernels: "auto" (the compiled kernels for
    float32 on the CPU, else the torch code), "compiled" (an error where they cannot run), "torch"
    (the reference path; `block` and `budget` apply to it only)."""

    antialias: str = DEFAULT_ANTIALIAS
    tile_size: int = 8
    block: int = 64
    budget: int = 1 << 21
    backward: str = "recompute"
    exact_tiles: bool = True
    dtype: torch.dtype = torch.float32
    kernels: str = "auto"


@dataclass
class RenderOutput:
    """One rendered view.

    image (H,W,3) and alpha (H,W): float tensors (image includes the background);
    depth (H,W): expected camera depth Σ wᵢ zᵢ / alpha (0 where nothing is drawn);
    radii (N,) int32: pixel radius of each Gaussian's opacity-aware footprint, 0 if culled;
    visible (N,) bool; means2d (N,2): projected centres (x = column, y = row, pixel centres at
    +0.5) in the autograd graph: call `means2d.retain_grad()` before `backward()` to get
    d loss / d means2d per Gaussian (what densification uses); num_pairs: tile-Gaussian pairs;
    num_evaluations: pixel-Gaussian alpha evaluations of the forward pass.
    """

    image: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    radii: torch.Tensor
    visible: torch.Tensor
    means2d: torch.Tensor
    num_pairs: int = 0
    num_evaluations: int = 0
    tile_size: int = 8


def _field(x, device) -> torch.Tensor:
    if is_torch(x):
        return x if device is None else x.to(device)
    a = np.ascontiguousarray(x)
    if a.dtype != np.float64:
        a = a.astype(np.float32, copy=False)
    t = torch.from_numpy(a)
    return t if device is None else t.to(device)


def antialias_parts(mode: str, cloud: GaussianCloud) -> tuple[bool, bool]:
    """(Mip-Splatting's 3D filter on, 2D Mip filter on) of an anti-aliasing mode for `cloud`
    (both False for "classic" and "matched"; `resolve_antialias` tells these apart)."""
    resolved = resolve_antialias(mode, cloud)
    return (resolved == "mip" and FILTER_KEY in cloud.extra, resolved == "mip")


def _size(cloud: GaussianCloud, key: str, device) -> torch.Tensor:
    size = _field(cloud.extra[key], device)
    if size.numel() != len(cloud):
        raise ValueError(f"render: extra[{key!r}] must hold one value per Gaussian, got shape "
                         f"{tuple(size.shape)} for {len(cloud)} Gaussians")
    return size.reshape(-1)


def project_view(cloud: GaussianCloud, camera: Camera, settings: RenderSettings, *, sh_degree: int | None = None,
                 device=None) -> tuple[Projected, torch.Tensor]:
    """Every Gaussian of `cloud` projected through `camera` with the anti-aliasing of `settings`
    (`render`'s arguments), and the packed table `render` composites: `prepare_view` without the
    tile lists (what is visible, and where)."""
    if not isinstance(camera, Camera):
        raise ValueError(f"render: camera must be a gvae_core.Camera, got {type(camera).__name__}")
    degree = cloud.sh_degree if sh_degree is None else int(sh_degree)
    if not 0 <= degree <= 3:
        raise ValueError(f"render: sh_degree must be 0..3, got {sh_degree}")
    degree = min(degree, cloud.sh_degree)
    mode = resolve_antialias(settings.antialias, cloud)
    f = {name: _field(getattr(cloud, name), device) for name in
         ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")}
    key = FILTER_KEY if mode == "mip" and FILTER_KEY in cloud.extra else DILATION_KEY if mode == "matched" else None
    if key is not None:
        f[SIZE] = _size(cloud, key, f["means"].device)
    if mode != "classic":  # a refined cloud's changes, for the octaves above its training rate it is drawn at
        f = drawn_fields(f, cloud, camera)
    dev = f["means"].device
    filter_3d = f[SIZE] if key == FILTER_KEY else None
    dilation_3d = f[SIZE] if key == DILATION_KEY else None
    fields = (f["means"], f["scales"], f["quats"], f["opacities"], f["sh_dc"], f["sh_rest"])
    if compiled.use_compiled(settings.kernels, dev, settings.dtype):
        proj, table = compiled.project(*fields, camera, degree, filter_3d=filter_3d, mip_2d=mode == "mip",
                                       dilation_3d=dilation_3d)
        if table.requires_grad:  # the centres as a view of their own, so that gradients reach means2d
            table = torch.cat([torch.cat([proj.means2d, proj.means2d.new_zeros(1, 2)]), table[:, 2:]], 1)
        return proj, table
    proj = project(*fields, camera, degree, dtype=settings.dtype, filter_3d=filter_3d, mip_2d=mode == "mip",
                   dilation_3d=dilation_3d)
    return proj, pack(proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths)


def prepare_view(cloud: GaussianCloud, camera: Camera, settings: RenderSettings, *, sh_degree: int | None = None,
                 device=None) -> tuple[Projected, Binning, torch.Tensor]:
    """What `render` (same arguments) composites: `project_view`'s projection and packed table, and
    the tile lists."""
    proj, table = project_view(cloud, camera, settings, sh_degree=sh_degree, device=device)
    if compiled.use_compiled(settings.kernels, table.device, settings.dtype):
        binning = compiled.bin_gaussians(table, proj.footprint, proj.visible, camera.width, camera.height,
                                         settings.tile_size, exact=settings.exact_tiles)
    else:
        binning = bin_gaussians(proj.means2d, proj.footprint, proj.depths, proj.visible, camera.width,
                                camera.height, settings.tile_size, exact=settings.exact_tiles)
    return proj, binning, table


def render(cloud: GaussianCloud, camera: Camera, *, background=(0.0, 0.0, 0.0), sh_degree: int | None = None,
           device=None, settings: RenderSettings | None = None) -> RenderOutput:
    """Render `cloud` (numpy or torch; gradients reach every torch field that requires grad)
    through `camera`. `sh_degree` limits the SH bands used (default: all the cloud has);
    `settings.antialias` says how the cloud's stored anti-aliasing sizes are used
    (`gvae_core.antialias`: "filter_3D" in the "mip" mode, "gvae_dilation_3D" in "matched")."""
    s = settings or RenderSettings()
    proj, binning, table = prepare_view(cloud, camera, s, sh_degree=sh_degree, device=device)
    h, w = camera.height, camera.width
    acc = composite(table, binning, block=s.block, budget=s.budget, backward=s.backward, kernels=s.kernels)
    learned_bg = isinstance(background, torch.Tensor) and background.requires_grad
    if compiled.use_compiled(s.kernels, acc.device, acc.dtype) and not learned_bg:
        image, alpha, depth = compiled.assemble(acc, binning, h, w, background)
    else:
        acc = tiles_to_image(acc, binning, h, w)
        bg = torch.as_tensor(background, dtype=s.dtype, device=acc.device).reshape(3)
        alpha = acc[..., 4]
        image = acc[..., :3] + (1.0 - alpha)[..., None] * bg
        drawn = alpha > 1e-6
        depth = torch.where(drawn, acc[..., 3] / torch.where(drawn, alpha, torch.ones_like(alpha)),
                            torch.zeros_like(alpha))
    return RenderOutput(image=image, alpha=alpha, depth=depth, radii=proj.radii, visible=proj.visible,
                        means2d=proj.means2d, num_pairs=binning.num_pairs,
                        num_evaluations=binning.evaluations, tile_size=s.tile_size)


def resolve_device(device=None):
    """The torch device to train and render on (`None`: the CPU), refused with a clear error when
    this machine or this torch build cannot use it (the pinned torch is a CPU build; a CUDA build
    and a GPU are needed for "cuda")."""
    try:
        dev = torch.device(device or "cpu")
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"unknown torch device {device!r}: {exc}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} requested, but this torch ({torch.__version__}) sees no CUDA GPU")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ValueError(f"device {device!r} requested, but only {torch.cuda.device_count()} CUDA device(s)")
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device {device!r}: only 'cpu' and 'cuda[:N]' are supported")
    return dev
