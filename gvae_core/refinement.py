"""Refinement past the training resolution (DESIGN.md step 5), two methods:

- "detail" (the default): the detail model (`gvae_core.detail`, trained through the renderer
  against real higher-resolution images) says how each Gaussian the budget selects should change
  per octave of sampling rate above the one it was trained at; the changes are stored with the
  cloud (`gvae_core.octaves`) and the renderer applies them by how far above its training rate
  each Gaussian is drawn, so the training-resolution picture is the input's by construction.
  `steps` is the number of octaves the changes run to. No Gaussian is added.
- "vae" (the paper's): score the input Gaussians (Hessian), pick the budget's share, and run the
  lineage VAEs for `steps` sequential steps: each step extends every lineage selected so far by
  one stage. The budget says where to densify: the selected Gaussians all densify at the first
  step; the models say how (how many children, where, how large, what colour) and, at later
  steps, whether each descendant densifies again, as they learned from progressive training.
  Later steps change geometry only (children carry their parent's appearance,
  `carry_appearance`). With the budget "all" every Gaussian is given to the models, which decide
  at every step. For a lineage, the existing slot nearest its last node updates that Gaussian in
  place; every other existing slot becomes a new Gaussian (appended after the input rows).
  Outputs are sanitised: finite, unit quaternions, log-scales and opacity logits inside finite
  ranges.
Last, for either, every lineage whose Gaussians change the picture at the training sampling rate
by more than `fidelity` is put back as it was (`gvae_core.fidelity`).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from collections.abc import Callable, Iterator, Sequence

import numpy as np
import torch

from .antialias import DILATION_KEY, FILTER_KEY, with_dilation_3d
from .budget import select_budget
from .camera import Camera
from .capture import default_views, scoring_views
from .cloud import PARAMETER_FIELDS, GaussianCloud
from .detail import DetailModel, detail_inputs, load_detail
from .detail.persistence import CONFIG as DETAIL_CONFIG
from .fidelity import DEFAULT_TOLERANCES, lineage_changes, revert_lineages, training_rate_views
from .hessian import DEFAULT_RESOLUTION, DEFAULT_VIEWS, hessian_scores, scoring_settings
from .lineage import (APP_EXIST, GEO_EXIST, GEO_LOG_SCALE, GEO_POSITION, Lineage, appearance_features,
                      cloud_from_features, geometry_features)
from .octaves import has_octaves, octave_fields, with_octaves
from .rendering.frames import Frame
from .resources import check_image_fit_memory, check_refine_memory, reuse_freed_memory
from .superres import SuperResConfig, SuperResFit, capture_images, fit_octaves
from .vae import GaussianVAE, load_default_model, load_model
from .vae.features import FEATURE_LOG_SCALE_RANGE, FEATURE_POSITION_LIMIT


@dataclass
class RefineResult:
    """The refined cloud (input rows first, in input order, then the added ones; extra properties
    as `GaussianCloud.append_children` gives them), which rows were added, each added row's
    ancestor row in the input, the step that added it, the input's Hessian scores, the input rows
    the budget selected, seconds per part, the lineage stage the input was matched to, and the
    selected rows whose lineages the fidelity check put back as they were."""

    cloud: GaussianCloud
    added: np.ndarray
    parents: np.ndarray
    step: np.ndarray
    scores: np.ndarray
    selected: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    #: The lineage stage the input was matched to (None without a lineage).
    stage: int | None = None
    #: Selected input rows left as they were: their lineages changed the training-rate picture.
    reverted: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    #: What the summary should say besides the counts (e.g. where the training rate came from).
    notes: dict[str, str] = field(default_factory=dict)
    #: The fit to the capture's images (`refine_images`), else None.
    fit: SuperResFit | None = None

    @property
    def n_input(self) -> int:
        return len(self.cloud) - len(self.added)

    def summary(self) -> str:
        times = ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in self.timings.items())
        notes = "".join(f"; {k}: {v}" for k, v in self.notes.items())
        if has_octaves(self.cloud):
            octaves = float(np.max(self.cloud.extra["gvae_octave_limit"], initial=0.0))
            children = f", {len(self.added)} added (drawn only above it)" if len(self.added) else ""
            return (f"{self.n_input} Gaussians, {len(self.selected)} selected, {len(self.reverted)} of them put back "
                    f"(fidelity), the others changed for up to {octaves:g} octave(s) above their training "
                    f"resolution{children}{notes}; {times}")
        per_step = np.bincount(self.step, minlength=int(self.step.max(initial=0)) + 1)[1:]
        return (f"{self.n_input} Gaussians in, {len(self.selected)} selected, {len(self.reverted)} of them put "
                f"back (fidelity), {len(self.added)} added "
                f"(per step: {', '.join(str(int(c)) for c in per_step) or '-'}), {len(self.cloud)} out{notes}; "
                f"{times}")


@dataclass(frozen=True)
class RefineInput:
    """A refine's input, converted and measured once at its entry (`refine` makes it and hands it to
    the method): the cloud as numpy arrays, refused if any row is not finite, and its normalisation
    (`GaussianCloud.normalization`: the frame of Hessian positions, of lineages without history and
    of the placed views)."""

    cloud: GaussianCloud
    normalization: tuple[np.ndarray, float]

    @classmethod
    def of(cls, cloud: GaussianCloud | RefineInput) -> RefineInput:
        if isinstance(cloud, RefineInput):
            return cloud
        src = cloud.numpy()
        bad = src.nonfinite_rows()
        if len(bad):
            rows = ", ".join(str(int(r)) for r in bad[:5])
            raise ValueError(f"refine: the cloud has non-finite values in {len(bad)} row(s) "
                             f"[{rows}{', ...' if len(bad) > 5 else ''}]; sanitize it first")
        return cls(src, src.normalization())


def _initial_history(cloud: GaussianCloud, lineage: Lineage | None, selected: np.ndarray, normalization):
    """Node features (M,T,11), (M,T,50) of the selected rows, and the normalisation's scale. The
    last node is always the input Gaussian itself; earlier nodes come from the lineage when given
    (whose last stage is the cloud: `_lineage_for`). Without a lineage the selected rows are
    one-node lineages (as `Lineage.from_cloud` makes them) in the frame of the whole cloud,
    `normalization`."""
    sub = cloud.select(selected)
    center, scale = normalization if lineage is None else (lineage.center, lineage.scale)
    geo = geometry_features(sub, center, scale)[:, None]
    app = appearance_features(sub)[:, None]
    if lineage is not None and lineage.n_stages > 1:
        last = lineage.n_stages - 1
        seq = lineage.sequences(last)
        ids = cloud.extra.get("gvae_id")
        if ids is not None and len(ids) == len(cloud):
            rows = lineage.rows_of(last, ids)  # sequences() keeps the snapshot's order
            if (rows < 0).any():
                raise ValueError(f"refine: {int((rows < 0).sum())} Gaussian id(s) of the cloud are not alive at the "
                                 f"lineage's stage {last}")
        elif len(seq) == len(cloud):
            rows = np.arange(len(cloud))
        else:
            raise ValueError(f"refine: the lineage's stage {last} has {len(seq)} Gaussians but the cloud has "
                             f"{len(cloud)} (and no gvae_id property to match them)")
        rows = rows[selected]
        geo = np.concatenate([seq.geometry[rows, :-1], geo], 1)
        app = np.concatenate([seq.appearance[rows, :-1], app], 1)
    return geo, app, float(scale)


def _lineage_for(cloud: GaussianCloud, lineage: Lineage, stage: int | None) -> tuple[Lineage, int]:
    """The lineage up to the stage the cloud comes from (`stage`, else `Lineage.stage_of`): a
    stage PLY of a run that went on to later stages is refined with the history it had then."""
    if stage is None:
        try:
            stage = lineage.stage_of(cloud)
        except ValueError as exc:
            raise ValueError(f"refine: the cloud does not match the lineage: {exc}") from None
    elif not 0 <= int(stage) < lineage.n_stages:
        raise ValueError(f"refine: stage {stage} is not in the lineage's stages 0..{lineage.n_stages - 1}")
    else:
        ids = cloud.extra.get("gvae_id")
        if ids is not None and len(ids) == len(cloud):
            missing = int((lineage.rows_of(int(stage), ids) < 0).sum())
            if missing:
                raise ValueError(f"refine: {missing} Gaussian id(s) of the cloud are not alive at the lineage's "
                                 f"stage {stage}")
        elif len(lineage.snapshot(int(stage))) != len(cloud):
            raise ValueError(f"refine: the lineage's stage {stage} has {len(lineage.snapshot(int(stage)))} Gaussians "
                             f"but the cloud has {len(cloud)} (and no gvae_id property to match them)")
    stage = int(stage)
    return (lineage if stage == lineage.n_stages - 1 else lineage.prefix(stage + 1)), stage


#: The refine methods (module docstring); `refine` uses DEFAULT_METHOD unless told.
METHODS = ("detail", "vae")
DEFAULT_METHOD = "detail"
#: Each method's budget unless told: the detail model changes every Gaussian (its changes are
#: small where nothing is to gain; BENCHMARKS.md "Refinement that improves the picture"), the
#: VAEs densify the Hessian's high-score class.
DEFAULT_BUDGETS = {"detail": "all", "vae": "auto"}
#: A cloud with neither an anti-aliasing size nor capture cameras is taken to have been trained by
#: cameras like the placed views at this image height (a typical capture's).
ASSUMED_TRAINING_HEIGHT = 1080


def refine(cloud: GaussianCloud, *, steps: int = 1, budget: Any = None, method: str | None = None,
           model: Any = None, cameras: Sequence[Camera] | None = None, lineage: Lineage | None = None,
           stage: int | None = None, seed: int = 0, progress: Callable[[float, str], None] | None = None,
           hessian_options: dict | None = None, scores: Any = None, carry_appearance: bool = True,
           check_memory: bool = True, fidelity: float | str | None = "auto", images: Any = None,
           image_height: int | None = None, fit: SuperResConfig | dict | None = None,
           test_every: int | None = None) -> RefineResult:
    """Refine `cloud` with `method` (module docstring; default: the one `model` is for, else
    DEFAULT_METHOD): "detail" changes the Gaussians the budget
    selects for up to `steps` (>= 1) octaves above their training resolution, "vae" runs `steps`
    sequential model steps on them. `budget` (see `select_budget`; default: the method's,
    DEFAULT_BUDGETS). `model`: a `DetailModel` / `GaussianVAE` or a model directory (default: the
    bundled one). `cameras`: the capture's cameras (`gvae_core.capture.load_cameras`): for the
    Hessian (a few are picked and scaled down, `capture.scoring_views`) and, for a cloud without an
    anti-aliasing size, as its training cameras; default: views placed around the cloud
    (`capture.default_views`). `lineage`: the training lineage of the cloud (default: one-node
    lineages); `stage`: the lineage stage the cloud is a snapshot of (default: found from its
    `gvae_id`s and positions, `Lineage.stage_of`; later stages are not used). `scores`:
    precomputed Hessian scores (skips scoring). `carry_appearance` ("vae"): after the first step
    the model changes geometry only, every child taking its parent's colour, SH and opacity (fed
    its own predictions, the model's appearance changes compounded and PSNR above the training
    resolution fell with every step in the v1 experiment). `progress(fraction, message)` is called
    as the work goes on; an exception it raises stops the refine (how the Blender job cancels).
    `check_memory`: refuse, with `resources.NotEnoughMemoryError`, a cloud whose estimated peak
    memory exceeds what is free. `fidelity`: the largest colour change (0..1) a lineage may make
    at the training sampling rate, seen from the scoring views; lineages above it are put back as
    they were (`gvae_core.fidelity`; "auto": the method's, DEFAULT_TOLERANCES; None: keep
    everything the models did). `images` (the detail method): the capture's training images, a
    dataset folder (`capture.load_capture_images`) or `Views` (`refine_images`), at
    `image_height` (default: the training resolution the cloud's anti-aliasing size says), every
    `test_every`-th held out as training held it out (those are never fitted); `fit`
    how the changes are fitted to them (a `superres.SuperResConfig` or a dict of its fields).
    Raises ValueError on non-finite input rows."""
    if method is None:
        method = _method_of(model)
    if method not in METHODS:
        raise ValueError(f"refine: method must be one of {', '.join(METHODS)}, got {method!r}")
    if isinstance(model, (GaussianVAE, DetailModel)) and isinstance(model, GaussianVAE) != (method == "vae"):
        raise ValueError(f"refine: a {type(model).__name__} cannot refine with the {method!r} method")
    budget = DEFAULT_BUDGETS[method] if budget is None else budget
    fidelity = DEFAULT_TOLERANCES[method] if isinstance(fidelity, str) and fidelity == "auto" else fidelity
    common = dict(steps=steps, budget=budget, model=model, cameras=cameras, lineage=lineage, stage=stage,
                  progress=progress, hessian_options=hessian_options, scores=scores, check_memory=check_memory,
                  fidelity=fidelity)
    if images is not None and method != "detail":
        raise ValueError(f"refine: images are fitted by the detail method (changes per octave), not by {method!r}")
    if images is None and (image_height is not None or fit is not None or test_every is not None):
        raise ValueError("refine: image_height, fit and test_every need images")
    _check_steps(steps)
    with reuse_freed_memory():  # one scope over all the parts: memory is handed back once, at the end
        src = RefineInput.of(cloud)
        if images is not None:
            result = refine_images(src, images, steps=steps, image_height=image_height, config=fit, model=model,
                                   lineage=lineage, stage=stage, progress=progress, check_memory=check_memory,
                                   test_every=test_every)
        elif method == "detail":
            result = refine_detail(src, **common)
        else:
            (result,) = refine_steps(src, seed=seed, every_step=False, carry_appearance=carry_appearance, **common)
    # the refined cloud is drawn over what the input was trained over
    result.cloud = result.cloud.replace(background=cloud.background)
    return result


def _method_of(model) -> str:
    """The method a model is for: a `GaussianVAE`, or a directory with only the VAEs' files, is
    "vae"; anything else DEFAULT_METHOD."""
    if isinstance(model, GaussianVAE):
        return "vae"
    if isinstance(model, (str, os.PathLike)):
        folder = Path(model)
        if not (folder / DETAIL_CONFIG).is_file() and (folder / "config.json").is_file():
            return "vae"
    return DEFAULT_METHOD


def _check_steps(steps) -> None:
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ValueError(f"refine: steps must be an integer >= 1, got {steps!r}")


def _check_memory(src: GaussianCloud, budget, options: dict, steps: int, scoring: bool, check_memory: bool,
                  method: str = "vae") -> None:
    """Refuse a cloud too large for the memory free now before any work."""
    n = len(src)
    if check_memory:
        extra = sum(int(np.prod(np.shape(v)[1:], dtype=np.int64)) for v in src.extra.values())
        if isinstance(budget, str) or isinstance(budget, (bool, np.bool_)):
            selected_bound = n if budget == "all" else None  # auto: at most half
        elif isinstance(budget, (int, np.integer)):
            selected_bound = min(n, max(int(budget), 0))
        else:
            try:
                selected_bound = min(n, int(np.ceil(float(budget) * n)))
            except (TypeError, ValueError, OverflowError):  # refused with its reason by select_budget
                selected_bound = None
        check_refine_memory(n, src.sh_degree, extra_values=extra, views=options.get("views", DEFAULT_VIEWS),
                            resolution=options.get("resolution", DEFAULT_RESOLUTION), selected=selected_bound,
                            steps=steps, scoring=scoring, method=method)


def _scores(src: GaussianCloud, cameras, scores, budget, options: dict, normalization, frames, say, h0, h1):
    """The Hessian scores (computed unless given; zeros with the budget "all"), finite, float32."""
    n = len(src)
    if scores is None and budget == "all":
        scores = np.zeros(n, np.float32)  # every Gaussian is refined: nothing to rank
    if scores is None:
        with reuse_freed_memory():
            scores = hessian_scores(src, cameras, normalization=normalization, frames=frames,
                                    progress=lambda f, message: say(h0 + (h1 - h0) * f, message), **options)
    scores = np.nan_to_num(np.asarray(scores.detach().cpu() if torch.is_tensor(scores) else scores,
                                      np.float32).reshape(-1), nan=0.0, posinf=0.0, neginf=0.0)
    if len(scores) != n:
        raise ValueError(f"refine: {len(scores)} scores for {n} Gaussians")
    return scores


def with_training_rate(cloud: GaussianCloud, cameras: Sequence[Camera] | None = None,
                       options: dict | None = None, normalization=None) -> tuple[GaussianCloud, str]:
    """The cloud with the anti-aliasing size the detail method needs to know its training sampling
    rate, and where that came from: the cloud's own; else its `cameras` (the capture's, at their
    size); else views placed around it (`capture.default_views`) at ASSUMED_TRAINING_HEIGHT."""
    if {FILTER_KEY, DILATION_KEY} & set(cloud.extra):
        return cloud, "stored"
    if cameras is not None:
        return with_dilation_3d(cloud, list(cameras)), "capture cameras"
    views = (options or {}).get("views", DEFAULT_VIEWS) or DEFAULT_VIEWS
    placed = default_views(cloud, views, ASSUMED_TRAINING_HEIGHT, normalization=normalization)
    return with_dilation_3d(cloud, placed), f"assumed: placed views at {ASSUMED_TRAINING_HEIGHT} px"


#: Why the detail method leaves a cloud trained with Mip-Splatting's 3D filter as it is.
NOT_FOR_FILTERED = ("the cloud carries a 3D filter (filter_3D, Mip-Splatting); the detail model was trained on "
                    "classic 3DGS clouds and lowered PSNR at 2x on one trained with the filter (-2.3 dB, "
                    "BENCHMARKS.md), so nothing was changed")


def refine_detail(cloud: GaussianCloud | RefineInput, *, steps: int = 1, budget: Any = "all", model: Any = None,
                  cameras: Sequence[Camera] | None = None, lineage: Lineage | None = None, stage: int | None = None,
                  progress: Callable[[float, str], None] | None = None, hessian_options: dict | None = None,
                  scores: Any = None, check_memory: bool = True,
                  fidelity: float | None = DEFAULT_TOLERANCES["detail"]) -> RefineResult:
    """`refine` with the detail method (the same arguments). The result's cloud carries the
    changes per octave (`gvae_core.octaves`; `octaves.bake` for other tools) and, when the input
    had none, the anti-aliasing size they are drawn by (`with_training_rate`; where it came from
    is in `RefineResult.notes`); nothing is added."""
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    say = progress or (lambda fraction, message: None)
    _check_steps(steps)
    inp = RefineInput.of(cloud)
    src, normalization = inp.cloud, inp.normalization
    n = len(src)
    options = dict(hessian_options or {})
    scoring = scores is None and budget != "all"
    _check_memory(src, budget, options, steps, scoring, check_memory, method="detail")
    empty = np.zeros(0, np.int64)
    if FILTER_KEY in src.extra:
        say(1.0, f"not refined: {NOT_FOR_FILTERED}")
        return RefineResult(cloud=src, added=empty, parents=empty, step=empty, scores=np.zeros(n, np.float32),
                            selected=empty, timings={"total": time.perf_counter() - t_start},
                            notes={"not refined": NOT_FOR_FILTERED})
    used_stage = None
    if lineage is not None:
        lineage, used_stage = _lineage_for(src, lineage, stage)
    t0 = time.perf_counter()
    model = model if isinstance(model, DetailModel) else load_detail(model)
    timings["load"] = time.perf_counter() - t0

    h0, h1 = (0.02, 0.75) if scoring else (0.02, 0.05)
    say(h0, "scoring Gaussians (Hessian)" if scoring else "reading the cloud")
    src, rate_source = with_training_rate(src, cameras, options, normalization)
    frames: list | None = [] if fidelity is not None else None
    t0 = time.perf_counter()
    scores = _scores(src, cameras, scores, budget, options, normalization, frames, say, h0, h1)
    timings["hessian"] = time.perf_counter() - t0
    selected = select_budget(scores, budget)

    say(h1, f"detail model: {len(selected)} Gaussians")
    t0 = time.perf_counter()
    inputs = detail_inputs(src, lineage, neighbours=model.config.inputs_neighbours, rows=selected)
    timings["features"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    predicted = model.changes(inputs)
    changes = {}
    for name, values in predicted.items():
        full = np.zeros((n,) + values.shape[1:], np.float32)
        full[selected] = values
        changes[name] = full
    out = with_octaves(src, changes, limit=float(steps))
    timings["model"] = time.perf_counter() - t0
    result = RefineResult(cloud=out, added=empty, parents=empty, step=empty, scores=scores, selected=selected,
                          timings=timings, stage=used_stage, notes={"training rate": rate_source})
    timings["total"] = time.perf_counter() - t_start
    if fidelity is not None and len(selected):
        say(0.97, "checking the training-resolution picture")
        result = FidelityCheck.around(src, cameras, fidelity, options, normalization, frames or ())(result)
    say(1.0, result.summary())
    return result


def refine_images(cloud: GaussianCloud | RefineInput, images: Any, *, steps: int = 1, image_height: int | None = None,
                  config: SuperResConfig | dict | None = None, model: Any = None, lineage: Lineage | None = None,
                  stage: int | None = None, progress: Callable[[float, str], None] | None = None,
                  check_memory: bool = True, test_every: int | None = None) -> RefineResult:
    """`refine` from the capture's own images (DESIGN.md step 5b, `gvae_core.superres`): every
    Gaussian's changes per octave, for octaves 1..`steps`, fitted so that the cloud drawn at 2^k
    times the images' resolution and area-averaged back down reproduces each image; starting from
    the detail model's prediction (`config.start`); children that fade in above the training
    rate where the fit asks for more Gaussians (`config.children`). The images are checked
    against the cloud first (`superres.capture_images`: the training resolution from
    `image_height`, else from the cloud's anti-aliasing size against their cameras). The
    training-resolution picture is the input's by construction."""
    t_start = time.perf_counter()
    say = progress or (lambda fraction, message: None)
    _check_steps(steps)
    config = SuperResConfig(**config) if isinstance(config, dict) else config or SuperResConfig()
    inp = RefineInput.of(cloud)
    src = inp.cloud
    n = len(src)
    _check_memory(src, "all", {}, steps, False, check_memory, method="detail")
    timings: dict[str, float] = {}
    say(0.01, "reading the capture's images")
    t0 = time.perf_counter()
    extra = sum(int(np.prod(np.shape(v)[1:], dtype=np.int64)) for v in src.extra.values())

    def memory(count: int, height: int, width: int) -> None:
        if check_memory:
            check_image_fit_memory(n, src.sh_degree, images=count, height=height, width=width, extra_values=extra,
                                   children=config.max_children if config.children is not None else 0.0,
                                   octaves=steps, patch=config.patch, views_per_step=config.views_per_step)

    capture = capture_images(src, images, image_height, before_loading=memory, test_every=test_every)
    src, views = capture.cloud, capture.views
    timings["images"] = time.perf_counter() - t0
    start = None
    if config.start == "detail" and FILTER_KEY not in src.extra:  # the model is not for filter-trained clouds
        say(0.03, "detail model")
        t0 = time.perf_counter()
        start = octave_fields(refine_detail(RefineInput(src, inp.normalization), steps=steps, model=model,
                                            lineage=lineage, stage=stage, fidelity=None, check_memory=False).cloud)
        timings["detail"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    fitted = fit_octaves(src, views, steps, config, start=start, background=capture.match.background,
                         progress=lambda f, message: say(0.05 + 0.93 * f, message))
    timings["fit"] = time.perf_counter() - t0
    kept = fitted.improves  # else what the held-out images liked better: the changes it started from, or none
    out = with_octaves(src, fitted.changes if fitted.kept in ("fit", "begin") else
                       {"start": start or {}, "input": {}}[fitted.kept], limit=float(steps))
    parents = fitted.child_roots if kept else np.zeros(0, np.int64)
    if len(parents):
        out = out.append_children(fitted.children, parents)
    timings["total"] = time.perf_counter() - t_start
    bg = "white" if capture.match.background[0] > 0.5 else "black"
    notes = {"training resolution": capture.height_source,
             "images": f"{len(views)} over a {bg} background (the cloud reproduces them at "
                       f"{capture.match.psnr:.1f} dB)",
             "fit": f"{fitted.images} images fitted, drawn at 2x and averaged down {fitted.psnr_before:.2f} -> "
                    f"{fitted.psnr_after:.2f} dB PSNR ({fitted.psnr_views} of them), loss "
                    f"{np.mean(fitted.losses[-50:]) if fitted.losses else float('nan'):.4f}",
             "judged on": fitted.judged()}
    if not kept:
        instead = {"begin": "the changes it began from, drawn with the anti-aliasing of the rate refined to",
                   "start": "the detail model's changes" if start else "the input as it was",
                   "input": "the input as it was"}[fitted.kept]
        notes["fit"] += f"; no better than {instead}, so not kept: {instead} instead"
        notes["kept"] = instead
    result = RefineResult(cloud=out, added=np.arange(n, len(out), dtype=np.int64), parents=parents,
                          step=np.ones(len(parents), np.int64), scores=np.zeros(n, np.float32),
                          selected=np.arange(n, dtype=np.int64), timings=timings, notes=notes, fit=fitted)
    say(1.0, result.summary())
    return result


def refine_steps(cloud: GaussianCloud | RefineInput, *, steps: int = 1, budget: Any = "auto", model: Any = None,
                 cameras: Sequence[Camera] | None = None, lineage: Lineage | None = None, stage: int | None = None,
                 seed: int = 0, progress: Callable[[float, str], None] | None = None,
                 hessian_options: dict | None = None, scores: Any = None, every_step: bool = True,
                 carry_appearance: bool = True, check_memory: bool = True,
                 fidelity: float | None = DEFAULT_TOLERANCES["vae"]) -> Iterator[RefineResult]:
    """`refine` with the "vae" method, yielding the result after every step (+1, +2, ...; each one
    the same as `refine` with that many steps and the same seed), or only after the last with
    `every_step=False`."""
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    say = progress or (lambda fraction, message: None)
    _check_steps(steps)
    inp = RefineInput.of(cloud)
    src, normalization = inp.cloud, inp.normalization
    options = dict(hessian_options or {})
    scoring = scores is None and budget != "all"
    _check_memory(src, budget, options, steps, scoring, check_memory)
    used_stage = None
    if lineage is not None:
        lineage, used_stage = _lineage_for(src, lineage, stage)

    t0 = time.perf_counter()
    if model is None:
        model = load_default_model()
    elif not isinstance(model, GaussianVAE):
        model = load_model(model)
    timings["load"] = time.perf_counter() - t0

    # progress: scoring (when there is any) takes most of the time
    h0, h1 = (0.02, 0.75) if scoring else (0.02, 0.05)
    say(h0, "scoring Gaussians (Hessian)")
    t0 = time.perf_counter()
    # the input as the Hessian's views composited it, for the fidelity check
    frames: list | None = [] if fidelity is not None else None
    scores = _scores(src, cameras, scores, budget, options, normalization, frames, say, h0, h1)
    timings["hessian"] = time.perf_counter() - t0
    selected = select_budget(scores, budget)

    t0 = time.perf_counter()
    hist_g, hist_a, scale = _initial_history(src, lineage, selected, normalization)
    timings["features"] = time.perf_counter() - t0

    gen = torch.Generator().manual_seed(int(seed))
    grow = _Growth(src, selected, hist_g, hist_a, scale)
    check = None
    if fidelity is not None and len(selected):
        check = FidelityCheck.around(src, cameras, fidelity, options, normalization, frames or ())
    del frames  # the check keeps the ones it uses
    for k in range(1, steps + 1):
        result = None
        with reuse_freed_memory():  # (not held while the caller has the result)
            say(h1 + (0.97 - h1) * (k - 1) / steps, f"step {k}/{steps}: {len(grow.rows)} lineages")
            if len(grow.rows):
                # The budget chose these Gaussians to densify at the first step; later steps (and
                # every step with "all") let the model decide, lineage by lineage.
                grow.step(k, model, None if budget == "all" or k > 1 else np.ones(len(grow.rows), bool), gen,
                          more=k < steps, carry_appearance=carry_appearance and k > 1)
            if every_step or k == steps:
                if k == steps:
                    say(0.97, "assembling the refined cloud")
                result = grow.result(scores, {**timings}, t_start)
                result.stage = used_stage
                if check is not None:
                    say(0.97 if k == steps else h1 + (0.97 - h1) * k / steps,
                        "checking the training-resolution picture")
                    result = check(result)
        if result is not None:
            if k == steps:
                say(1.0, result.summary())
            suspended = time.perf_counter()
            yield result
            t_start += time.perf_counter() - suspended  # the caller's time is not ours


class FidelityCheck:
    """Puts back the lineages of a result that change the picture at the training sampling rate by
    more than `tolerance` (`gvae_core.fidelity`); keeps the input's frames, made once where a view
    needs them (or by the Hessian), and redraws them with each result's changes."""

    def __init__(self, src: GaussianCloud, cameras: list[Camera], tolerance: float, settings=None,
                 frames: Sequence[Frame] = ()):
        if not tolerance >= 0.0:
            raise ValueError(f"refine: fidelity must be a tolerance >= 0 or None, got {tolerance!r}")
        self.src, self.cameras, self.tolerance = src, cameras, tolerance
        self.settings = scoring_settings(settings)
        self.frames = [next((f for f in frames if _same_view(f.camera, cam) and f.settings == self.settings), None)
                       for cam in cameras]

    @classmethod
    def around(cls, src: GaussianCloud, cameras, tolerance: float, hessian_options: dict | None = None,
               normalization=None, frames: Sequence[Frame] = ()) -> FidelityCheck:
        """The check `refine` makes: the Hessian's views (the capture's `cameras` picked and scaled
        as for scoring, else views placed around the cloud; DEFAULT_VIEWS of them when the Hessian
        takes all, views=0, which would cost two renders each) at the training sampling rate: the
        cloud's stored anti-aliasing size says what it was, else the capture's cameras at their
        full size do (a cloud from another tool with its cameras), else the views stay as they are.
        `frames`: the input's frames that the Hessian made (`hessian_scores`), used where a view is
        the same instead of projecting and binning the input again."""
        options = hessian_options or {}
        views = options.get("views", DEFAULT_VIEWS) or DEFAULT_VIEWS
        resolution = options.get("resolution", DEFAULT_RESOLUTION)
        cams = (scoring_views(cameras, views, resolution, src) if cameras is not None
                else default_views(src, views, resolution, normalization=normalization or src.normalization()))
        rate_of = src
        if cameras is not None and not {FILTER_KEY, DILATION_KEY} & set(src.extra):
            rate_of = with_dilation_3d(src, list(cameras))
        return cls(src, training_rate_views(rate_of, cams), float(tolerance), options.get("render_settings"),
                   frames)

    def __call__(self, result: RefineResult) -> RefineResult:
        t0 = time.perf_counter()
        # the input's frames are made where a view needs them (lineage_changes stores them for the next result)
        change = lineage_changes(self.src, result.cloud, result.selected, result.added, result.parents,
                                 self.cameras, settings=self.settings, frames=self.frames)
        reverted = result.selected[change > self.tolerance]
        cloud, kept = revert_lineages(self.src, result.cloud, result.n_input, result.parents, reverted)
        n = result.n_input
        timings = {**result.timings, "fidelity": time.perf_counter() - t0}
        timings["total"] = timings.get("total", 0.0) + timings["fidelity"]
        return RefineResult(cloud=cloud, added=np.arange(n, n + int(kept.sum()), dtype=np.int64),
                            parents=result.parents[kept], step=result.step[kept], scores=result.scores,
                            selected=result.selected, timings=timings, stage=result.stage, reverted=reverted,
                            notes=result.notes)


def _same_view(a: Camera, b: Camera) -> bool:
    """Whether two cameras draw the same image."""
    return ((a.width, a.height, a.fx, a.fy, a.cx, a.cy) == (b.width, b.height, b.fx, b.fy, b.cx, b.cy)
            and np.array_equal(a.world_to_cam, b.world_to_cam))


class _Growth:
    """The lineages being extended, step after step, and what they have added so far."""

    def __init__(self, src: GaussianCloud, selected: np.ndarray, hist_g: np.ndarray, hist_a: np.ndarray,
                 scale: float):
        self.src, self.selected, self.scale = src, selected, scale
        self.hist_g, self.hist_a = hist_g, hist_a
        self.rows = selected.copy()     # current-cloud row of each active lineage
        self.roots = selected.copy()    # its ancestor row in the input
        self.world = src.means[selected].astype(np.float64)  # exact world positions of the last nodes
        self.new_parts: list[GaussianCloud] = []
        self.updates: list[tuple[np.ndarray, GaussianCloud]] = []  # (rows, new values), in step order
        self.added_parents: list[np.ndarray] = []  # ancestor rows in the input
        self.born_from: list[np.ndarray] = []      # rows (of the output) of the Gaussians they came from
        self.added_steps: list[np.ndarray] = []
        self.n_total = len(src)
        self.model_time = 0.0

    def _cloud(self, geometry: np.ndarray, appearance: np.ndarray, world: np.ndarray) -> GaussianCloud:
        """Predicted nodes as raw, finite, bounded Gaussians at exact world positions."""
        return cloud_from_features(geometry, appearance, 0.0, self.scale, self.src.sh_degree, means=world,
                                   bounded=True)

    def step(self, k: int, model, densify, gen: torch.Generator, more: bool = True,
             carry_appearance: bool = False) -> None:
        """Extend every active lineage by one predicted stage (and, when `more` steps follow,
        make the lineages of the next one)."""
        t0 = time.perf_counter()
        max_nodes = max(model.geometry.config.max_nodes, model.appearance.config.max_nodes)
        g, a, p, _ = model.predict(self.hist_g[:, -max_nodes:], self.hist_a[:, -max_nodes:], densify, generator=gen)
        g, a, p = g.numpy().astype(np.float64), a.numpy(), p.numpy()
        if carry_appearance:  # every slot takes the last node's appearance; existence stays the model's
            a[..., :APP_EXIST] = self.hist_a[:, -1, None, :APP_EXIST]
        self.model_time += time.perf_counter() - t0
        last = self.hist_g[:, -1].astype(np.float64)
        size = np.exp(np.clip(last[:, GEO_LOG_SCALE], *FEATURE_LOG_SCALE_RANGE).mean(1))
        last_pos = np.clip(np.nan_to_num(last[:, GEO_POSITION]), -FEATURE_POSITION_LIMIT, FEATURE_POSITION_LIMIT)
        dist = np.linalg.norm(g[..., GEO_POSITION] - last_pos[:, None], axis=-1) / size[:, None]
        # Existence is sampled (seeded): thresholding at 0.5 would never add a child whose
        # probability is below one half, under-generating systematically.
        exists = torch.rand(p.shape, generator=gen).numpy() < p
        keeper = np.argmin(np.where(exists, dist, np.inf), 1)
        # World positions: the parent's exact world position plus the predicted offset.
        child_world = self.world[:, None] + (g[..., GEO_POSITION] - last_pos[:, None]) * self.scale
        # Updated parents (the nearest existing slot), then the extra slots as new Gaussians.
        upd = np.flatnonzero(exists.any(1))
        ks = keeper[upd]
        if len(upd):
            self.updates.append((self.rows[upd], self._cloud(g[upd, ks], a[upd, ks], child_world[upd, ks])))
        extra = exists.copy()
        extra[upd, ks] = False
        li, si = np.nonzero(extra)
        new_rows = self.n_total + np.arange(len(li))
        if len(li):
            self.new_parts.append(self._cloud(g[li, si], a[li, si], child_world[li, si]))
            self.added_parents.append(self.roots[li])
            self.born_from.append(self.rows[li])
            self.added_steps.append(np.full(len(li), k, np.int64))
            self.n_total += len(li)
        if not more:
            self.rows = self.rows[:0]
            return
        # Next step's lineages: updated parents and their new siblings, one node longer.
        g_node = g.astype(np.float32)
        g_node[..., GEO_EXIST] = 1.0
        a[..., APP_EXIST] = 1.0
        cont = np.concatenate([upd, li])
        slot = np.concatenate([ks, si])
        prev_g, prev_a = self.hist_g[cont], self.hist_a[cont]  # fancy indexing copies
        prev_g[len(upd):, :, GEO_EXIST] = 0.0
        prev_a[len(upd):, :, APP_EXIST] = 0.0
        self.hist_g = np.concatenate([prev_g, g_node[cont, slot][:, None]], 1)
        self.hist_a = np.concatenate([prev_a, a[cont, slot][:, None]], 1)
        self.world = child_world[cont, slot]
        self.rows = np.concatenate([self.rows[upd], new_rows])
        self.roots = np.concatenate([self.roots[upd], self.roots[li]])

    def result(self, scores: np.ndarray, timings: dict, t_start: float) -> RefineResult:
        """The input rows (with in-place updates applied in step order) followed by the added ones."""
        t0 = time.perf_counter()
        added = GaussianCloud.concat(self.new_parts) if self.new_parts else GaussianCloud.empty(self.src.sh_degree)
        out = self.src.append_children(added, np.concatenate([np.zeros(0, np.int64)] + self.born_from))  # copies
        for rows, values in self.updates:
            for name in PARAMETER_FIELDS:
                getattr(out, name)[rows] = getattr(values, name)
        timings.update(model=self.model_time, assemble=time.perf_counter() - t0)
        timings["total"] = time.perf_counter() - t_start
        return RefineResult(
            cloud=out, added=np.arange(len(self.src), len(out), dtype=np.int64),
            parents=np.concatenate(self.added_parents) if self.added_parents else np.zeros(0, np.int64),
            step=np.concatenate(self.added_steps) if self.added_steps else np.zeros(0, np.int64),
            scores=scores, selected=self.selected, timings=timings)
