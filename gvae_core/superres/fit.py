"""Multi-view super-resolution: every Gaussian's changes per octave (`gvae_core.octaves`) fitted so
that the cloud drawn at 2^k times the training resolution and area-averaged 2^k x 2^k back down
reproduces each training image.

The area average is how the images at the training resolution were made (or nearly: a camera
integrates over its pixel), so the real image at 2^k times the resolution satisfies this loss
exactly; the unrefined cloud, fitted as point samples at the training resolution, does not. Each
image sees the surface at its own sub-pixel offset and distance; together they constrain detail
finer than any one of them resolves. At the training resolution nothing is drawn changed (by
construction), so the picture the images were fitted with stays the input's.

A fit is judged on images it did not fit: every `holdout`-th image is held out, the fit runs on
the rest, and the held-out ones, drawn at 2x and averaged down, are checked every `check_every`
passes: a fit that draws them more than `tolerance` dB worse than its best is taken back to its
best and goes on at `slow_down` times its rates (a second fall stops it there); and the fit is
kept only if it draws them better than the changes it started from (its step 0), else the better
of the detail model's changes and the input as it was
(`SuperResFit.kept`). A fit that reproduces its own images better proves nothing (on a real capture
it did, and drew the photos it did not see no better). The held-out images are at the training
resolution: what they see of a fit is its changes' side effects there, not the detail it adds above
it (their figure can peak early or fall while the 2x picture keeps improving), so they guard
against a fit that goes wrong, and do not choose the step it stops at: it runs its steps unless they
trip the guard. Where the defaults come from: docs/benchmarks/refine-images.md.

Each step draws `views_per_step` (image, tile) pairs (whole images by default; tiles that cover
each image with `patch`; every pixel visited once a pass), an octave k, renders at 2^k times the
image's resolution with the changes (every Gaussian takes the octaves above its own training rate
the view samples it at), averages down and back-propagates 0.8 L1 + 0.2 (1 - SSIM) into the
changes (and into the per-image guards, `guards`, when on). Adam (`VisibleAdam`: only the rows a
step saw move) at `lr` times the reference 3DGS learning rates of each field; `pull` draws the
changes a step saw back towards where they started (decoupled, as AdamW's weight decay), so that
they grow no larger than the images keep asking for. With `children`, the 3DGS densification rule
on the fit's view-space gradients adds Gaussians that fade in above the training rate (`children`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from ..antialias import DILATION_KEY, FILTER_KEY
from ..camera import Camera, scene_extent
from ..cloud import GaussianCloud
from ..conventions import activate_opacities
from ..datasets import Views, every_nth
from ..densify import g_scale
from ..detail.fit import ORACLE_LEARNING_RATES, crop
from ..losses import psnr
from ..octaves import FIELDS, REFINED_SIZE_CHANGE, SIZE, with_octaves
from ..rendering import RenderOutput, RenderSettings, render
from ..train.photometric import photometric_loss
from ..train.strategy import DensifyStrategy
from .children import CHILD_LOGIT, densify
from .guards import ExposureCorrection, PoseCorrection
from .optim import VisibleAdam

__all__ = ["SuperResConfig", "SuperResFit", "fit_octaves", "holdout_rows", "DEFAULT_FIELDS", "CHILD_GRADIENT"]

#: What the fit changes unless told: every field, rotations and SH bands included.
DEFAULT_FIELDS = ("scales", "opacities", "sh_dc", "means", "quats", "sh_rest")
#: The view-space gradient at which the fit adds children when asked (`SuperResConfig.children`):
#: the reference 3DGS's densification threshold.
CHILD_GRADIENT = DensifyStrategy.grad_threshold
#: A child's own parameters. Its opacity at the training rate is CHILD_LOGIT and its centre there is
#: the one of the input Gaussian it comes from (both fixed): it sees every camera as that Gaussian
#: does, so it is drawn changed exactly where that Gaussian is; its change per octave moves it out.
_CHILD_FIELDS = ("scales", "quats", "sh_dc", "sh_rest")
#: Children whose opacity one octave up ends below this are dropped (the reference's prune level).
CHILD_MIN_OPACITY = 0.005
#: The optimisers a fit can run (`SuperResConfig.optimizer`).
OPTIMIZERS = {"visible": VisibleAdam, "adam": torch.optim.Adam}


@dataclass
class SuperResConfig:
    """epochs: passes over the fitted images (every pixel, each octave), up to `max_steps` optimiser
    steps per octave; steps: the steps per octave instead (None: from `epochs`); patch: edge of
    the square tiles that cover each image, a step fitting one, in pixels at the images'
    resolution (0: whole images); views_per_step: (image, tile) pairs whose gradients one step
    sums; fields: what changes per octave; lr: times the reference 3DGS learning rate of each
    field, decaying exponentially to `lr_final` times that by the last step (the reference's
    schedule for positions); pull: the share of its distance from where it started a seen change
    gives back each step (0: none); holdout: every n-th image (of the images given, in their order)
    judges the fit instead of being fitted (0, or fewer than 16 images: none, the fitted images
    judge it); check_every: passes between checks on them; tolerance: how far (dB) below their best
    figure the fit may draw them before it is taken back to its best; slow_down: the fit then goes
    on from there at this fraction of its rates, with fresh moments (once; a second fall, or 0,
    stops it there); pose / exposure:
    the penalty weight of the per-image guard (`guards`), None: off; children: the view-space gradient (NDC, the
    reference's units) at which a Gaussian densifies (`CHILD_GRADIENT`, the reference 3DGS's), None
    (the default): no children; densify_at: when, as fractions of the steps; max_children: at most
    this many children per input Gaussian; start: where the changes start, "detail" (the detail
    model's prediction, `gvae_core.refine` makes it) or "zero"; size_change: every Gaussian's
    anti-aliasing size's change per octave of its logarithm (`octaves.SIZE`; default: drawn with
    the anti-aliasing of the rate it is refined to, halved per octave; None: the anti-aliasing it
    was trained with); optimizer: "visible" (`optim.VisibleAdam`: only the rows a step saw move) or
    "adam" (torch's plain Adam, for comparison)."""

    epochs: float = 20.0
    max_steps: int = 300
    steps: int | None = None
    patch: int = 0
    views_per_step: int = 1
    fields: tuple[str, ...] = DEFAULT_FIELDS
    lr: float = 1.0
    lr_final: float = 1.0
    pull: float = 0.0
    holdout: int = 8
    check_every: float = 0.5
    tolerance: float = 1.0
    slow_down: float = 0.3
    lambda_dssim: float = 0.2
    pose: float | None = None
    exposure: float | None = None
    children: float | None = None
    densify_at: tuple[float, ...] = (0.25, 0.5)
    max_children: float = 0.5
    start: str = "detail"
    size_change: float | None = REFINED_SIZE_CHANGE
    seed: int = 0
    antialias: str = "auto"
    optimizer: str = "visible"

    def __post_init__(self):
        self.fields = tuple(self.fields)
        self.densify_at = tuple(float(x) for x in self.densify_at)
        unknown = [f for f in self.fields if f not in FIELDS]
        if unknown:
            raise ValueError(f"superres: unknown field(s) {', '.join(unknown)}; known: {', '.join(FIELDS)}")
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"superres: optimizer must be one of {', '.join(OPTIMIZERS)}, got {self.optimizer!r}")
        if self.start not in ("detail", "zero"):
            raise ValueError(f"superres: start must be 'detail' or 'zero', got {self.start!r}")
        if (self.steps is not None and int(self.steps) < 0) or int(self.patch) < 0 or not self.epochs >= 0:
            raise ValueError(f"superres: steps, epochs and patch must be >= 0, got {self.steps}, {self.epochs}, "
                             f"{self.patch}")
        if int(self.views_per_step) < 1 or not 0 <= self.pull < 1 or int(self.holdout) < 0 \
                or not self.check_every > 0 or not self.tolerance >= 0 or not 0 <= self.slow_down < 1:
            raise ValueError("superres: views_per_step must be >= 1, holdout and tolerance >= 0, check_every > 0, "
                             f"pull and slow_down in [0, 1), got {self.views_per_step}, {self.holdout}, "
                             f"{self.tolerance}, {self.check_every}, {self.pull}, {self.slow_down}")


@dataclass
class SuperResFit:
    """The kept changes per octave of the input rows (field -> numpy array shaped like the field;
    what `kept` says), the children (a numpy cloud of their parameters at their training rate,
    with their changes per octave as `gvae_octave_*` extras, and each one's input row it came from),
    the loss of every step, PSNR (dB, octave 1: drawn at 2x and averaged down) on the held-out
    images (`holdout_views` of them; NaN without) of the input as it was, of the detail model's
    changes (`start`), of the fit at its step 0 (those changes and the anti-aliasing of the rate it
    is refined to) and at the state it ends in, and the same on `psnr_views` of the fitted images
    before and after; which state was kept ("fit" when it draws the held-out images better than its
    step 0, else the best on them of "begin" (step 0: `changes` are then those), "start" and "input";
    without held-out images the fitted ones decide between "fit" and "start"),
    the step of the fit's state, the steps run and planned, the step after which it went on at
    `slow_down` times its rates (0: never), every check on the held-out images (step, PSNR), the
    per-image guards' state, and seconds."""

    changes: dict[str, np.ndarray]
    losses: list[float]
    psnr_before: float
    psnr_after: float
    psnr_views: int
    psnr_start: float = float("nan")
    images: int = 0
    holdout_views: int = 0
    holdout_input: float = float("nan")
    holdout_start: float = float("nan")
    holdout_begin: float = float("nan")
    holdout_fit: float = float("nan")
    kept: str = "fit"
    fit_step: int = 0
    steps_run: int = 0
    steps_planned: int = 0
    slowed_at: int = 0
    checks: list[tuple[int, float]] = field(default_factory=list)
    children: GaussianCloud | None = None
    child_roots: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    pose_pixels: np.ndarray | None = None
    exposure_gains: np.ndarray | None = None
    seconds: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def improves(self) -> bool:
        """Whether the fit's changes are the ones kept (it draws the held-out images, else its own,
        better than where it began)."""
        return self.kept == "fit"

    def judged(self) -> str:
        """One line: what judged the fit and what it said."""
        if self.holdout_views:
            return (f"{self.holdout_views} held-out images drawn at 2x and averaged down: input "
                    f"{self.holdout_input:.2f}, detail model {self.holdout_start:.2f}, the fit at step 0 "
                    f"{self.holdout_begin:.2f} and at step {self.fit_step} {self.holdout_fit:.2f} dB PSNR "
                    f"({self.steps_run} of {self.steps_planned} steps run"
                    + (f"; back to its best and slower from step {self.slowed_at}" if self.slowed_at else "")
                    + f"); kept: {self.kept}")
        return (f"no images held out: its own images {self.psnr_start:.2f} (start) -> {self.psnr_after:.2f} dB; "
                f"kept: {self.kept}")


class _Model:
    """What the fit changes: the input rows (fixed) with their changes per octave, and the children
    (their own parameters and changes), with the optimiser over all of them."""

    def __init__(self, src: GaussianCloud, fields: list[str], start: dict | None, lrs: dict[str, float],
                 optimizer=VisibleAdam):
        key = FILTER_KEY if FILTER_KEY in src.extra else DILATION_KEY
        self.key = key
        self.base = src.replace(extra={key: src.extra[key]}).to_torch()
        self.n = len(src)
        self.changes = {}
        for f in fields:
            init = torch.zeros_like(getattr(self.base, f))
            if start is not None and f in start:
                init = torch.as_tensor(np.asarray(start[f], np.float32)).reshape(init.shape).clone()
            self.changes[f] = init.requires_grad_(True)
        self.fixed = {f: torch.as_tensor(np.asarray(v, np.float32)) for f, v in (start or {}).items()
                      if f not in self.changes}
        self.child = {f: getattr(self.base, f)[:0].clone().requires_grad_(True) for f in _CHILD_FIELDS}
        self.roots = torch.zeros(0, dtype=torch.int64)
        self.means64 = np.ascontiguousarray(self.base.means.double().numpy().T)  # (3, R): the rows' fixed centres
        self.lrs = lrs
        self.optimizer = optimizer
        self.opt = self._optimizer(1.0)

    def _optimizer(self, factor: float) -> VisibleAdam:
        """Adam, no moments yet, on the changes as they are, at `factor` times the rates."""
        return self.optimizer([{"params": [p], "lr": self.lrs[f] * factor} for f, p in self.changes.items()]
                           + [{"params": [p], "lr": self.lrs[f] * factor} for f, p in self.child.items()], eps=1e-15)

    @property
    def m(self) -> int:
        return len(self.roots)

    def rows(self) -> GaussianCloud:
        """Input rows then children, as drawn at the training rate (torch; children's opacity CHILD_LOGIT)."""
        if not self.m:
            return self.base
        b = self.base
        fields = {f: torch.cat([getattr(b, f), self.child[f]]) for f in _CHILD_FIELDS}
        fields["means"] = torch.cat([b.means, b.means[self.roots]])
        fields["opacities"] = torch.cat([b.opacities, torch.full((self.m,), CHILD_LOGIT)])
        return GaussianCloud(**fields, extra={self.key: torch.cat([b.extra[self.key], b.extra[self.key][self.roots]])})

    def all_changes(self) -> dict[str, torch.Tensor]:
        """Every row's changes per octave: the fitted ones, and the fixed ones (a child takes its
        input Gaussian's)."""
        fixed = {f: torch.cat([v, v[self.roots]]) for f, v in self.fixed.items()}
        return {**fixed, **self.changes}

    def cloud(self, limit: float, camera: Camera | None = None) -> tuple[GaussianCloud, torch.Tensor | None]:
        """The rows with their changes up to `limit` octaves; with `camera`, only the rows that can
        reach its image (`_reaching`), and which they are (None: all)."""
        rows, changes = self.rows(), self.all_changes()
        if camera is None:
            return with_octaves(rows, changes, limit=limit), None
        if self.means64.shape[1] != len(rows):
            self.means64 = np.ascontiguousarray(rows.means.double().numpy().T)
        keep = torch.from_numpy(_reaching(self.means64, _reach(rows, changes, limit), camera))
        sub = rows.select(keep)
        return with_octaves(sub, {f: v[keep] for f, v in changes.items()}, limit=limit), keep

    def state_one_octave_up(self) -> dict[str, torch.Tensor]:
        """Every row's parameters as drawn one octave above its training rate (detached)."""
        rows = self.rows()
        changes = self.all_changes()
        return {f: (getattr(rows, f) + changes[f] if f in changes else getattr(rows, f)).detach()
                for f in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")}

    def grow(self, grads: torch.Tensor, threshold: float, room: int, extent: float, gen: torch.Generator) -> int:
        """One round of densification (`children.densify`); returns the number of children added.
        Needs the opacity among the fitted fields (a child fades in by its change), and the centres
        and scales to split (else Gaussians are cloned)."""
        if room <= 0 or "opacities" not in self.changes:
            return 0
        state = self.state_one_octave_up()
        can_split = "means" in self.changes and "scales" in self.changes
        d = densify(state, grads, threshold, room, extent, gen, percent_dense=0.01 if can_split else float("inf"))
        if not len(d.rows):
            return 0
        rows_at_rate = self.rows()
        roots = torch.where(d.rows < self.n, d.rows, self.roots[(d.rows - self.n).clamp(min=0)]
                            if self.m else d.rows)
        with torch.no_grad():
            changes = self.all_changes()
            if can_split:  # a split Gaussian becomes the first of its two children one octave up
                rows = d.rows[d.split]
                self.changes["means"][rows] = d.parent_means[d.split] - rows_at_rate.means[rows]
                inputs, kids = rows[rows < self.n], rows[rows >= self.n]
                scales = d.parent_scales[d.split]
                self.changes["scales"][inputs] = scales[rows < self.n] - self.base.scales[inputs]
                self.child["scales"][kids - self.n] = scales[rows >= self.n] - changes["scales"][kids]
        new_changes = {f: torch.zeros((len(d.rows),) + tuple(p.shape[1:])) for f, p in self.changes.items()}
        new_changes["opacities"] = d.children["opacities"] - CHILD_LOGIT
        if "means" in new_changes:
            new_changes["means"] = d.children["means"] - self.base.means[roots]
        for f, p in self.changes.items():
            self.changes[f] = self._extend(p, new_changes[f])
        for f, p in self.child.items():
            self.child[f] = self._extend(p, d.children[f])
        self.roots = torch.cat([self.roots, roots])
        return len(d.rows)

    def snapshot(self) -> dict:
        """The fitted state (changes, children), to return to (`restore`)."""
        with torch.no_grad():
            return {"changes": {f: p.detach().clone() for f, p in self.changes.items()},
                    "child": {f: p.detach().clone() for f, p in self.child.items()}, "roots": self.roots.clone()}

    def restore(self, state: dict, rates: float | None = None) -> None:
        """Back to a `snapshot`; with `rates`, a fresh optimiser at that fraction of the rates to go on
        from there (else the optimiser is not used after this)."""
        self.changes = {f: v.clone().requires_grad_(True) for f, v in state["changes"].items()}
        self.child = {f: v.clone().requires_grad_(True) for f, v in state["child"].items()}
        self.roots = state["roots"].clone()
        if rates is not None:
            self.opt = self._optimizer(rates)

    def pull(self, towards: dict[str, torch.Tensor], share: float, seen: torch.Tensor) -> None:
        """Move the input rows' changes `seen` (bool, input rows) `share` of the way back to
        `towards` (their start): decoupled from Adam's step, as AdamW's weight decay."""
        with torch.no_grad():
            rows = torch.nonzero(seen[:self.n]).reshape(-1)
            for f, p in self.changes.items():
                p[rows] -= share * (p[rows] - towards[f][rows])

    def _extend(self, old: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """`old` with `rows` appended, in its place in the optimiser (Adam moments zero for the new rows)."""
        new = torch.cat([old.detach(), rows.to(old.dtype)]).requires_grad_(True)
        for group in self.opt.param_groups:
            if group["params"][0] is old:
                group["params"][0] = new
        state = self.opt.state.pop(old, None)
        if state:
            for k in ("exp_avg", "exp_avg_sq"):
                s = state[k]
                state[k] = torch.cat([s, torch.zeros((len(rows),) + tuple(s.shape[1:]), dtype=s.dtype)])
            self.opt.state[new] = state
        return new

    def result(self, limit: float) -> tuple[dict[str, np.ndarray], GaussianCloud | None, np.ndarray]:
        """The input rows' changes, the children worth keeping (their opacity one octave up at least
        CHILD_MIN_OPACITY) as a numpy cloud with their changes as extras, and their input rows."""
        changes = {f: v.detach().numpy()[:self.n].copy() for f, v in self.all_changes().items()}
        if not self.m:
            return changes, None, np.zeros(0, np.int64)
        up = self.state_one_octave_up()
        keep = (activate_opacities(up["opacities"][self.n:]) >= CHILD_MIN_OPACITY).numpy()
        roots = self.roots.numpy()[keep]
        kids = GaussianCloud(**{f: self.child[f].detach()[keep].numpy() for f in _CHILD_FIELDS},
                             means=self.base.means.numpy()[roots],
                             opacities=np.full(int(keep.sum()), CHILD_LOGIT, np.float32))
        kid_changes = {f: v.detach()[self.n:][keep].numpy() for f, v in self.all_changes().items()}
        size = self.base.extra[self.key].numpy()[roots]
        kids = with_octaves(kids.replace(extra={self.key: size}), kid_changes, limit)
        return changes, kids.replace(extra={k: v for k, v in kids.extra.items() if k != self.key}), roots


def _reach(rows: GaussianCloud, changes: dict[str, torch.Tensor], limit: float) -> np.ndarray:
    """(R,) how far (world units) each row's footprint can reach from its centre at any octave up to
    `limit`: the renderer draws nothing beyond 3.33 standard deviations (alpha below 1/255), so 3.5
    of the largest axis at either end of the octaves, plus the anti-aliasing size and how far the
    centre moves."""
    with torch.no_grad():
        log_s = rows.scales.detach()
        if "scales" in changes:
            log_s = torch.maximum(log_s, log_s + limit * changes["scales"].detach())
        size = rows.extra[FILTER_KEY if FILTER_KEY in rows.extra else DILATION_KEY].reshape(-1)
        radius = 3.5 * log_s.clamp(max=20.0).exp().amax(1) + size
        if "means" in changes:
            radius = radius + limit * changes["means"].detach().norm(dim=1)
        return radius.double().numpy()


def _reaching(means: np.ndarray, radius: np.ndarray, camera: Camera) -> np.ndarray:
    """Indices of the rows (centres `means`: (3, R) float64 columns, reach `radius`, `_reach`) whose
    footprint can reach `camera`'s image: a patch is drawn from this subset exactly as from all of
    them, for a fraction of the cost on a large capture. Bounded generously: a 50% and 2-pixel
    margin, and every row at or around the camera kept."""
    r, t = camera.rotation, camera.translation
    x, y, z = (r[i, 0] * means[0] + r[i, 1] * means[1] + r[i, 2] * means[2] + t[i] for i in range(3))  # (a matmul
    near = z - radius < 0.05                                                                       # is 10x slower)
    reach = (1.5 * max(camera.fx, camera.fy)) * radius / np.where(near, 1.0, z - radius) + 2.0
    iz = 1.0 / np.where(near, 1.0, z)
    u = camera.fx * x * iz + camera.cx
    v = camera.fy * y * iz + camera.cy
    inside = (u + reach >= 0) & (u - reach <= camera.width) & (v + reach >= 0) & (v - reach <= camera.height)
    return np.flatnonzero((z + radius > 0.0) & (near | inside))


def _down(image: torch.Tensor, factor: int) -> torch.Tensor:
    """(H*f, W*f, C) -> (H, W, C), the mean of each f x f block."""
    if factor == 1:
        return image
    return F.avg_pool2d(image.permute(2, 0, 1)[None], factor)[0].permute(1, 2, 0)


def _draw(cloud: GaussianCloud, camera, factor: int, background: torch.Tensor, settings: RenderSettings,
          pose: PoseCorrection | None, exposure: ExposureCorrection | None,
          view: int) -> tuple[torch.Tensor, RenderOutput]:
    """The cloud drawn through `camera` (at `factor` times the image's resolution, cropped) and
    averaged back down, with image `view`'s guards; and the render."""
    if pose is not None:
        cloud = pose.apply(cloud, view)
    out = render(cloud, camera, background=background, settings=settings)
    image = out.image
    if exposure is not None:
        image = exposure.apply(image, out.alpha, background, view)
    return _down(image, factor), out


def training_psnr(cloud: GaussianCloud, views: Views, targets: torch.Tensor, background, factor: int,
                  settings: RenderSettings, rows) -> float:
    """Mean PSNR of the cloud drawn at `factor` times the images' resolution and averaged down,
    against the images `rows`."""
    bg = torch.as_tensor(background, dtype=torch.float32)
    with torch.no_grad():
        values = []
        for v in rows:
            cam = views.cameras[v]
            big = cam.scaled(cam.height * factor)
            values.append(psnr(_draw(cloud, big, factor, bg, settings, None, None, v)[0], targets[v]))
    return float(np.mean(values))


def holdout_rows(names, every: int) -> np.ndarray:
    """Which of the images named `names` judge a fit instead of being fitted: every `every`-th by
    name from the `every // 2`-th (`datasets.every_nth`; none with `every` 0, or fewer than
    2 * `every` images)."""
    if every <= 0 or len(names) < 2 * every:
        return np.zeros(0, np.int64)
    return every_nth(names, every, every // 2)


def _tiles(width: int, height: int, patch: int) -> list[tuple[int, int, int, int]]:
    """(x0, y0, w, h) tiles of edge `patch` covering a width x height image (the last row and column
    shifted inside it; one tile, the whole image, with `patch` 0 or at least the image)."""
    if not patch or patch >= max(width, height):
        return [(0, 0, width, height)]
    xs = sorted({min(x, width - patch) for x in range(0, width, patch)}) if patch < width else [0]
    ys = sorted({min(y, height - patch) for y in range(0, height, patch)}) if patch < height else [0]
    return [(x, y, min(patch, width), min(patch, height)) for y in ys for x in xs]


@dataclass
class _Images:
    """The images a fit reads and how it draws them: the targets over the background, which rows it
    fits, which judge it (`held`) and which say how well it draws its own (`checked`), and the
    factor the judges draw at (`first`: octave 1, or the images' own resolution)."""

    views: Views
    targets: torch.Tensor
    background: tuple
    bg: torch.Tensor
    settings: RenderSettings
    held: np.ndarray
    fitted: np.ndarray
    checked: np.ndarray
    first: int

    def judge(self, cloud: GaussianCloud, rows) -> float:
        """Mean PSNR of `cloud` on the images `rows` (NaN without any)."""
        if not len(rows):
            return math.nan
        return training_psnr(cloud, self.views, self.targets, self.background, self.first, self.settings, rows)


def _images(views: Views, config: SuperResConfig, background, images_scale: int, check_views: int) -> _Images:
    held = holdout_rows(views.names, int(config.holdout))
    fitted = np.setdiff1d(np.arange(len(views)), held)
    checked = fitted[np.linspace(0, len(fitted) - 1, min(check_views, len(fitted))).round().astype(int)]
    return _Images(views, torch.from_numpy(views.composite(background)), background,
                   torch.as_tensor(background, dtype=torch.float32), RenderSettings(antialias=config.antialias),
                   held, fitted, checked, max(2 // images_scale, 1))


@dataclass
class _Schedule:
    """The fit's steps: the octaves they take in turn, the (image, tile) pairs a pass visits, how
    many a step sums, the steps in all, the steps between checks and those after which it densifies."""

    octaves: list[int]
    units: list[tuple[int, tuple[int, int, int, int]]]
    per_step: int
    total: int
    check_interval: int
    densify_steps: set[int]
    images_scale: int
    image_size: tuple[int, int]  # (width, height)


def _schedule(config: SuperResConfig, images: _Images, octaves: int, images_scale: int) -> _Schedule:
    height, width = images.views.cameras[0].height, images.views.cameras[0].width
    octave_list = [k for k in range(1, octaves + 1) if 2 ** k >= images_scale]
    units = [(int(v), tile) for v in images.fitted for tile in _tiles(width, height, int(config.patch))]
    per_step = int(config.views_per_step)
    per_octave = (config.steps if config.steps is not None
                  else min(int(config.max_steps), math.ceil(config.epochs * len(units) / per_step)))
    total = int(per_octave) * len(octave_list)
    check_interval = max(1, math.ceil(config.check_every * len(units) / per_step) * len(octave_list))
    densify_steps = {int(round(f * total)) for f in config.densify_at} if config.children is not None else set()
    return _Schedule(octave_list, units, per_step, total, check_interval, densify_steps, images_scale,
                     (width, height))


@dataclass
class _Baseline:
    """What the fit is measured against, taken before its first step: PSNR of the checked fitted
    images at step 0 (`before`) and with the detail model's changes (`start`), and on the held-out
    images of the input as it was and of the detail model's changes."""

    before: float
    start: float
    holdout_input: float
    holdout_start: float


@dataclass
class _FitState:
    """What the fit carries from step to step: the model and per-image guards, where the changes
    started (`origin`, for the pull), the random streams, the rates the schedule decays from, the
    best check on the held-out images and its state, the state of step 0, and the record."""

    model: _Model
    origin: dict[str, torch.Tensor]
    pose: PoseCorrection | None
    exposure: ExposureCorrection | None
    rng: np.random.Generator
    gen: torch.Generator
    begin: float
    best: float
    best_state: dict
    initial_state: dict
    rates: list[float] = field(default_factory=list)
    best_step: int = 0
    stopped: bool = False
    slowed: int = 0
    checking: float = 0.0
    losses: list[float] = field(default_factory=list)
    checks: list[tuple[int, float]] = field(default_factory=list)
    order: list = field(default_factory=list)
    grad_sum: torch.Tensor | None = None
    grad_count: torch.Tensor | None = None


def _check_scale(octaves, images_scale: int) -> int:
    octaves = int(octaves)
    if octaves < 1:
        raise ValueError(f"superres: octaves must be >= 1, got {octaves}")
    if images_scale < 1 or images_scale & (images_scale - 1) or images_scale > 2 ** octaves:
        raise ValueError(f"superres: images_scale must be a power of 2 up to 2^octaves, got {images_scale}")
    return octaves


def _new_model(src: GaussianCloud, views: Views, config: SuperResConfig, start: dict, extent: float
               ) -> tuple[_Model, PoseCorrection | None, ExposureCorrection | None]:
    """The model of the changes at the configured rates, and the per-image guards asked for (their
    parameters in its optimiser)."""
    fields = [f for f in config.fields if getattr(src, f).size]
    lrs = {f: ORACLE_LEARNING_RATES[f] * config.lr * (extent if f == "means" else 1.0) for f in FIELDS}
    model = _Model(src, fields, start, lrs, OPTIMIZERS[config.optimizer])
    pose = exposure = None
    if config.pose is not None:
        pose = PoseCorrection(views.cameras, _median_depths(src, views), config.pose)
        model.opt.add_param_group({"params": [pose.params], "lr": 0.01})
    if config.exposure is not None:
        exposure = ExposureCorrection(len(views), config.exposure)
        model.opt.add_param_group({"params": [exposure.params], "lr": 0.005})
    return model, pose, exposure


def _baseline(model: _Model, src: GaussianCloud, start: dict, images: _Images, limit: float
              ) -> tuple[_Baseline, float]:
    """The figures before the first step, and the held-out PSNR of the fit's own start (the
    changes and the anti-aliasing of the rate they are refined to)."""
    given = with_octaves(src, {f: v for f, v in start.items() if f != SIZE}, limit=limit)
    before, start_psnr = images.judge(model.cloud(limit)[0], images.checked), images.judge(given, images.checked)
    holdout_input, holdout_start = images.judge(src, images.held), images.judge(given, images.held)
    begin = images.judge(model.cloud(limit)[0], images.held)
    return _Baseline(before, start_psnr, holdout_input, holdout_start), begin


def _fit_view(state: _FitState, scale: int, plan: _Schedule, images: _Images, config: SuperResConfig,
              limit: float, seen: torch.Tensor) -> float:
    """Draw the next (image, tile) pair at `scale` times the image's resolution, back-propagate
    its loss (a share of the step's), mark the rows it saw in `seen` and sum their view-space
    gradients when the fit densifies; returns its share of the step's loss."""
    model, pose, exposure = state.model, state.pose, state.exposure
    if not state.order:
        state.order = [plan.units[i] for i in state.rng.permutation(len(plan.units))]
    v, (x0, y0, w, h) = state.order.pop()
    cam = images.views.cameras[v]
    big = cam.scaled(cam.height * scale)
    full_size = (big.width, big.height)
    target = images.targets[v]
    if (w, h) != plan.image_size:  # a tile
        big = crop(big, x0 * scale, y0 * scale, w * scale, h * scale)
        target = target[y0:y0 + h, x0:x0 + w]
    cloud_now, subset = model.cloud(limit, big if pose is None else None)
    drawn, out = _draw(cloud_now, big, scale, images.bg, images.settings, pose, exposure, v)
    if plan.densify_steps:
        out.means2d.retain_grad()
    loss = photometric_loss(drawn, target, config.lambda_dssim, compiled=images.settings.kernels != "torch")
    total_loss = loss / plan.per_step
    if pose is not None:
        total_loss = total_loss + pose.penalty() / plan.per_step
    if exposure is not None:
        total_loss = total_loss + exposure.penalty() / plan.per_step
    total_loss.backward()
    visible = out.visible.detach()
    if subset is None:
        seen |= visible
    else:
        seen[subset[visible]] = True
    if plan.densify_steps and out.means2d.grad is not None:
        _add_gradients(state, out, visible, subset, full_size)
    return float(loss.detach()) / plan.per_step


def _add_gradients(state: _FitState, out: RenderOutput, visible: torch.Tensor, subset, full_size) -> None:
    """Sum the view-space gradient of every row the view saw (the densification rule's, in NDC)."""
    n = state.model.n + state.model.m
    if state.grad_sum is None or len(state.grad_sum) != n:
        state.grad_sum, state.grad_count = torch.zeros(n), torch.zeros(n)
    g = (out.means2d.grad.detach()[:, :2] * g_scale(*full_size)).norm(dim=-1)
    index = subset if subset is not None else slice(None)
    state.grad_sum[index] += g * visible.float()
    state.grad_count[index] += visible.float()


def _fit_step(state: _FitState, step: int, plan: _Schedule, images: _Images, config: SuperResConfig,
              limit: float, extent: float) -> None:
    """One optimiser step: its rates, `plan.per_step` views of one octave, the pull towards the
    start and, at a densification step, the children."""
    model = state.model
    if config.lr_final != 1.0:
        decay = config.lr_final ** (step / max(plan.total - 1, 1))
        for g, lr in zip(model.opt.param_groups, state.rates):
            g["lr"] = lr * decay
    octave = plan.octaves[step % len(plan.octaves)]
    scale = 2 ** octave // plan.images_scale  # render size over image size
    seen = torch.zeros(model.n + model.m, dtype=torch.bool)
    step_loss = 0.0
    for _ in range(plan.per_step):
        step_loss += _fit_view(state, scale, plan, images, config, limit, seen)
    model.opt.step()
    model.opt.zero_grad(set_to_none=True)
    if config.pull:
        model.pull(state.origin, config.pull, seen)
    state.losses.append(step_loss)
    if step + 1 in plan.densify_steps and state.grad_sum is not None:
        room = int(config.max_children * model.n) - model.m
        model.grow(state.grad_sum / state.grad_count.clamp(min=1.0), config.children, room, extent, state.gen)
        state.grad_sum = state.grad_count = None
        state.origin = {f: torch.cat([state.origin[f], torch.zeros_like(p[len(state.origin[f]):])])
                        if len(p) > len(state.origin[f]) else state.origin[f] for f, p in model.changes.items()}


def _check(state: _FitState, step: int, images: _Images, config: SuperResConfig, limit: float,
           on_check) -> bool:
    """Judge the fit on the held-out images after `step`: keep its best state; a fall of more than
    the tolerance takes it back there, on at a fraction of the rates once, and stops it the second
    time (returns True to stop)."""
    model = state.model
    t1 = time.perf_counter()
    now = images.judge(model.cloud(limit)[0], images.held)
    state.checking += time.perf_counter() - t1
    state.checks.append((step + 1, now))
    if on_check is not None:
        on_check(step + 1, model.cloud(limit)[0].detach())
    if now > state.best:
        state.best, state.best_state, state.best_step = now, model.snapshot(), step + 1
    elif now < state.best - config.tolerance:
        if state.slowed or not config.slow_down:
            state.stopped = True
            return True
        state.slowed = step + 1  # back to its best, on at a fraction of the rates
        model.restore(state.best_state, config.slow_down)
        state.rates = [g["lr"] for g in model.opt.param_groups]
    return False


def _kept(state: _FitState, baseline: _Baseline, images: _Images, fit_step: int, fit_psnr: float,
          after: float) -> str:
    """Which state the fit ends in (`SuperResFit.kept`); the model is put back to step 0 when that
    one is kept."""
    if not len(images.held):
        return "fit" if after > baseline.start else "start"
    if fit_step and fit_psnr > state.begin:
        return "fit"
    # not fitted: the best of where it began, the detail model's changes and the input
    others = {"begin": state.begin, "start": baseline.holdout_start, "input": baseline.holdout_input}
    kept = max(others, key=others.get)
    if kept == "begin":
        state.model.restore(state.initial_state)
    return kept


def fit_octaves(cloud: GaussianCloud, views: Views, octaves: int = 1, config: SuperResConfig | None = None, *,
                start: dict | None = None, background=(1.0, 1.0, 1.0), images_scale: int = 1,
                progress: Callable[[float, str], None] | None = None, check_views: int = 4,
                on_check: Callable[[int, GaussianCloud], None] | None = None) -> SuperResFit:
    """Fit `cloud`'s changes per octave (numpy cloud that knows its training rate: an anti-aliasing
    size) for octaves 1..`octaves` to `views` (the capture's images at the resolution the cloud
    was trained at, over `background`), judged on the ones held out (module docstring). `start`:
    changes to start from (field -> array; default zero). `images_scale`: the images are this power
    of 2 times the training resolution (2: real 2x images, the oracle of one octave; renders are
    averaged down to them). `progress(fraction, message)` after every step; an exception it raises
    stops the fit. `on_check(step, cloud)`: at every check, the cloud (torch, with the changes as
    they are then) for whoever wants to look at it too (a study of how the fit goes)."""
    config = config or SuperResConfig()
    t_start = time.perf_counter()
    octaves = _check_scale(octaves, images_scale)
    limit = float(octaves)
    src = cloud.numpy()
    extent = scene_extent(views.cameras)[1]
    start = dict(start or {})
    if config.size_change is not None:
        start[SIZE] = np.full(len(src), config.size_change, np.float32)
    model, pose, exposure = _new_model(src, views, config, start, extent)
    origin = {f: p.detach().clone() for f, p in model.changes.items()}
    images = _images(views, config, background, images_scale, check_views)
    rng = np.random.default_rng(config.seed)
    gen = torch.Generator().manual_seed(int(config.seed))

    t0 = time.perf_counter()
    baseline, begin = _baseline(model, src, start, images, limit)
    snapshot = model.snapshot()
    state = _FitState(model, origin, pose, exposure, rng, gen, begin=begin, best=begin, best_state=snapshot,
                      initial_state=snapshot, checks=[(0, begin)] if len(images.held) else [])
    if on_check is not None:
        on_check(0, model.cloud(limit)[0].detach())
    timings = {"check": time.perf_counter() - t0}
    plan = _schedule(config, images, octaves, images_scale)
    t0 = time.perf_counter()
    state.rates = [g["lr"] for g in model.opt.param_groups]
    step = 0
    for step in range(plan.total):
        _fit_step(state, step, plan, images, config, limit, extent)
        if progress is not None:  # every step: a step of a large capture takes seconds, and cancel acts here
            progress((step + 1) / max(plan.total, 1), f"fitting to the images: step {step + 1}/{plan.total}, "
                     f"loss {np.mean(state.losses[-20:]):.4f}"
                     + (f", held-out {state.best:.2f} dB" if len(images.held) else ""))
        if len(images.held) and ((step + 1) % plan.check_interval == 0 or step == plan.total - 1):
            if _check(state, step, images, config, limit, on_check):
                break
    steps_run = step + 1 if plan.total else 0
    timings["fit"] = time.perf_counter() - t0 - state.checking
    t0 = time.perf_counter()
    fit_step, fit_psnr = steps_run, state.checks[-1][1] if state.checks else math.nan
    if state.stopped:
        model.restore(state.best_state)
        fit_step, fit_psnr = state.best_step, state.best
    after = images.judge(model.cloud(limit)[0], images.checked)
    timings["check"] += state.checking + time.perf_counter() - t0
    kept = _kept(state, baseline, images, fit_step, fit_psnr, after)
    changes, children, roots = model.result(limit)
    return SuperResFit(changes=changes, losses=state.losses, psnr_before=baseline.before, psnr_after=after,
                       psnr_start=baseline.start, psnr_views=len(images.checked), images=len(images.fitted),
                       holdout_views=len(images.held), holdout_input=baseline.holdout_input,
                       holdout_start=baseline.holdout_start, holdout_begin=state.begin, holdout_fit=fit_psnr,
                       kept=kept, fit_step=fit_step, steps_run=steps_run, slowed_at=state.slowed,
                       checks=state.checks, steps_planned=plan.total, children=children, child_roots=roots,
                       pose_pixels=None if pose is None else pose.pixels(),
                       exposure_gains=None if exposure is None else exposure.gains(),
                       seconds=time.perf_counter() - t_start, timings=timings)


def _median_depths(src: GaussianCloud, views: Views) -> np.ndarray:
    """Each image's median camera depth of the Gaussians in front of it (the scale at which a
    translation of its camera moves the picture)."""
    out = []
    for cam in views.cameras:
        z = (src.means.astype(np.float64) - cam.center) @ cam.rotation[2]
        z = z[z > 0.01]
        out.append(float(np.median(z)) if len(z) else 1.0)
    return np.asarray(out)
