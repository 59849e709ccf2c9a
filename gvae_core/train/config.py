"""The trainer's configuration: `TrainConfig`, its named profiles and the schedules it implies.

Every field carries its help in its metadata (`help`, and `flag` where the command line names it
otherwise), from which `gvae train`'s flags and their help are made (`gvae_core.cli.fields`): a
default is said once, here. numpy only (`gvae --help` imports no torch).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..conventions import SH_REST_COUNTS
from ..initialization import INIT_MODES

__all__ = ["TrainConfig", "PROFILES", "ANTIALIAS_MODES", "LR_SCHEDULES", "stage_heights", "configure", "position_lr"]

ANTIALIAS_MODES = ("classic", "mip")
LR_SCHEDULES = ("run", "stage")

#: Profiles: overrides of the `TrainConfig` defaults. `default` is the benchmark profile.
PROFILES: dict[str, dict[str, Any]] = {
    # a quick look (and the tests'): fixed counts, no training on until convergence
    "tiny": dict(resolutions=(32, 48, 64), iterations=(200, 150, 150), init_count=2000,
                 max_gaussians=10_000, sh_degree=1, converge=False),
    "default": dict(),
    # fixed iterations, no validation photos, no budget, the learning rate and Adam afresh per stage
    "legacy": dict(iterations=(600, 400, 400), validation_views=0, converge=False, gaussians_per_pixel=None,
                   lr_schedule="stage", carry_optimizer=False, opacity_resets=True, average=None, cool_down=0,
                   depth_weight=0.0),
    # the reference's schedule
    "full": dict(resolutions=(100, 200, 400, 800), iterations=(7000, 7000, 7000, 30000),
                 init="random", init_count=100_000, max_gaussians=None),
}


def _f(default, help: str, **meta):
    """A field with its help (and command-line metadata: `flag`, `metavar`, `choices`,
    `zero_is_none`, `advanced`) for `gvae_core.cli.fields`."""
    return field(default=default, metadata={"help": help, **meta})


@dataclass
class TrainConfig:
    """Everything a progressive run depends on (JSON values; stored in run.json). Each field's help
    is in its metadata. Schedules given in `reference_iterations` units (the reference's 30k
    iterations) are scaled to each stage's count (`stage_schedule`)."""

    # the stages
    resolutions: tuple[int, ...] = _f((100, 150, 200), "training image heights, coarse to fine", metavar="H")
    iterations: tuple[int, ...] = _f(
        (300, 300, 1000), "iterations per stage, one count for all stages or one per stage; given, they are fixed "
        "(with --converge, the last stage's is its planned count, after which it trains on until the validation "
        "photos stop improving)", metavar="N")
    # learning rates (the reference 3DGS's; positions times the scene extent)
    position_lr_init: float = _f(1.6e-4, "position learning rate at the start, times the scene extent",
                                 advanced=True)
    position_lr_final: float = _f(1.6e-6, "position learning rate at the end of its decay, times the scene extent",
                                  advanced=True)
    feature_lr: float = _f(2.5e-3, "learning rate of the SH DC colour", advanced=True)
    feature_rest_lr: float = _f(2.5e-3 / 20.0, "learning rate of the higher SH coefficients", advanced=True)
    opacity_lr: float = _f(0.05, "learning rate of the opacity logits", advanced=True)
    scaling_lr: float = _f(5e-3, "learning rate of the log-scales", advanced=True)
    rotation_lr: float = _f(1e-3, "learning rate of the quaternions", advanced=True)
    lambda_dssim: float = _f(0.2, "weight of 1 - SSIM in the loss (the rest is L1)", advanced=True)
    depth_weight: float = _f(0.0, "weight in the loss of the rendered depth's relative error at the SfM points "
                             "each training photo sees (0: none; a capture without points has none)",
                             metavar="W")
    # spherical harmonics
    sh_degree: int = _f(3, "largest SH degree", choices=(0, 1, 2, 3))
    sh_interval: int = _f(1000, "the SH degree rises by one every this many reference iterations", advanced=True)
    # density control (reference values, in reference iterations)
    reference_iterations: int = _f(30_000, "the iteration count the schedules below are given for", advanced=True)
    densify_from: int = _f(500, "densification starts after this many reference iterations", advanced=True)
    densify_until: int = _f(15_000, "densification stops after this many reference iterations", advanced=True)
    densify_every: int = _f(100, "reference iterations between two rounds of densification", advanced=True)
    opacity_reset_every: int = _f(3000, "reference iterations between opacity resets; large Gaussians are pruned "
                                  "after the first interval", advanced=True)
    min_densify_every: int = _f(25, "the fewest iterations between two rounds of densification", advanced=True)
    min_opacity_reset_every: int = _f(300, "the fewest iterations between two opacity resets", advanced=True)
    densify_grad_threshold: float = _f(2e-4, "mean view-space positional gradient (NDC) above which a Gaussian "
                                       "is cloned or split", advanced=True)
    percent_dense: float = _f(0.01, "Gaussians larger than this fraction of the scene extent split, smaller "
                              "ones clone", advanced=True)
    prune_opacity: float = _f(0.005, "Gaussians below this opacity are pruned", advanced=True)
    max_world_size: float = _f(0.1, "Gaussians larger than this fraction of the scene extent are pruned",
                               advanced=True)
    max_screen_fraction: float | None = _f(None, "prune Gaussians whose screen radius exceeds this fraction of the "
                                           "image height (the reference's screen-size test never fires: off)",
                                           advanced=True, zero_is_none=True)
    reset_opacity_value: float = _f(0.01, "opacities come down to this at a reset", advanced=True)
    max_gaussians: int | None = _f(None, "a cap on the number of Gaussians (none: what memory allows)",
                                   zero_is_none=True)
    # data, initialisation, evaluation
    background: tuple[float, float, float] = _f(
        (1.0, 1.0, 1.0), "background colour images are composited on and the cloud is trained over, stored with it",
        metavar=("R", "G", "B"))
    init: str = _f("auto", "where training starts: sfm (the capture's SfM points, with random points where they "
                   "leave pixels uncovered), hull (inside the visual hull of transparent images' masks), random "
                   "(random points along the training rays) or auto: sfm, else hull for images with transparency, "
                   "else random", choices=INIT_MODES)
    init_count: int = _f(10_000, "number of random initial points")
    init_opacity: float = _f(0.1, "opacity of the initial Gaussians", advanced=True)
    train_eval_views: int = _f(10, "training views a stage's training PSNR is measured on", advanced=True)
    test_eval_views: int | None = _f(None, "held-out views a stage's held-out PSNR is measured on (none: all)",
                                     advanced=True, zero_is_none=True)
    seed: int = _f(0, "random seed")
    antialias: str = _f("classic", "classic (the reference 3DGS; stage PLYs get gvae_dilation_3D) or mip (train "
                        "with Mip-Splatting's 3D and 2D filters; stage PLYs get filter_3D)", choices=ANTIALIAS_MODES)
    test_every: int | None = _f(None, "hold out every N-th image by name as a test view, 8 as LLFF and Mip-NeRF 360 "
                                "do (none: a NeRF-Synthetic folder's own test split, or none)", metavar="N")
    # validation photos and convergence
    validation_views: int = _f(8, "training photos set aside (never trained on, at most one in eight) to judge "
                               "when training stops helping (0: none; the iterations are then fixed)", metavar="N")
    converge: bool = _f(True, "the last stage trains on past its planned iterations until the validation photos "
                        "stop improving, and keeps the state they liked best")
    max_iterations: int = _f(30_000, "the most iterations the last stage trains to while converging", advanced=True)
    validation_every: int = _f(100, "iterations between two draws of the validation photos", advanced=True)
    patience: int = _f(600, "converged once the validation PSNR has not risen by --min-gain for this many "
                       "iterations", advanced=True)
    min_gain: float = _f(0.05, "dB the validation PSNR must rise by to count as a gain", advanced=True)
    max_minutes: float | None = _f(None, "time budget of the whole run: the last stage stops when it is spent (once "
                                   "its planned iterations are done)", flag="--minutes", metavar="M")
    gaussians_per_pixel: float | None = _f(1.0, "a budget of this many Gaussians per pixel of one training photo in "
                                           "each stage (0: none)", zero_is_none=True, metavar="F")
    average: float | None = _f(0.99, "the last stage ends on the running average of its iterates, from the end of "
                               "its densification, with this decay (about the last 1 / (1 - decay) steps), and its "
                               "validation photos judge the average (0: the last iterate)", zero_is_none=True,
                               metavar="DECAY")
    cool_down: int = _f(1000, "once the last stage has converged, this many more iterations with Adam afresh and the "
                        "position learning rate decaying again from its start, ending on their running average; "
                        "kept when the validation photos like it better (0: none)", metavar="N")
    # across stages
    lr_schedule: str = _f("run", "the position learning rate decays over the whole run, or afresh in each stage",
                          choices=LR_SCHEDULES, advanced=True)
    carry_optimizer: bool = _f(True, "Adam's moments carry from a stage to the next (else they restart)",
                               advanced=True)
    opacity_resets: bool = _f(False, "the reference's periodic opacity reset", advanced=True)

    def __post_init__(self):
        self.resolutions = tuple(int(r) for r in np.atleast_1d(self.resolutions))
        its = tuple(int(i) for i in np.atleast_1d(self.iterations))
        if len(its) == 1 and len(self.resolutions) > 1:
            its = its * len(self.resolutions)
        self.iterations = its
        self.background = tuple(float(b) for b in self.background)
        self._check()

    def _check(self) -> None:
        def bad(what: str) -> None:
            raise ValueError(f"TrainConfig.{what}")
        if not self.resolutions or any(r <= 0 for r in self.resolutions):
            bad(f"resolutions must be positive image heights, got {self.resolutions}")
        if len(self.iterations) != len(self.resolutions) or any(i < 0 for i in self.iterations):
            bad(f"iterations must be one count >= 0 or one per stage ({len(self.resolutions)}), got {self.iterations}")
        if self.sh_degree not in SH_REST_COUNTS:
            bad(f"sh_degree must be 0..3, got {self.sh_degree}")
        for name, allowed in (("init", INIT_MODES), ("antialias", ANTIALIAS_MODES), ("lr_schedule", LR_SCHEDULES)):
            if getattr(self, name) not in allowed:
                bad(f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}")
        if self.test_every is not None and int(self.test_every) < 2:
            bad(f"test_every must be 2 or more, got {self.test_every}")
        if len(self.background) != 3:
            bad(f"background must be 3 values, got {self.background}")
        if self.validation_views < 0 or self.validation_every <= 0 or self.patience <= 0 or self.min_gain < 0:
            bad(f"validation_views must be >= 0, validation_every and patience positive, min_gain >= 0 (got "
                f"{self.validation_views}, {self.validation_every}, {self.patience}, {self.min_gain})")
        for name in ("max_minutes", "gaussians_per_pixel"):
            if getattr(self, name) is not None and not getattr(self, name) > 0:
                bad(f"{name} must be positive or None, got {getattr(self, name)}")
        if self.cool_down < 0 or not self.depth_weight >= 0:
            bad(f"cool_down and depth_weight must be >= 0, got {self.cool_down}, {self.depth_weight}")
        if self.average is not None and not 0.0 < self.average < 1.0:
            bad(f"average must be a decay in (0, 1) or None, got {self.average}")

    @classmethod
    def profile(cls, name: str = "default", **overrides) -> TrainConfig:
        """A named profile (`PROFILES`) with some fields overridden (None: the profile's)."""
        if name not in PROFILES:
            raise ValueError(f"unknown training profile {name!r}; choose from {sorted(PROFILES)}")
        return cls(**{**PROFILES[name], **{k: v for k, v in overrides.items() if v is not None}})

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        """The configuration `to_dict` wrote; an unknown field is an error."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"TrainConfig: unknown field(s) {', '.join(unknown)}")
        return cls(**d)

    def to_dict(self) -> dict[str, Any]:
        """Every field as JSON values."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    def at_height(self, height: int) -> TrainConfig:
        """The same run with its last stage at `height` and the others in proportion (`stage_heights`)."""
        return dataclasses.replace(self, resolutions=stage_heights(height, self.resolutions))

    def learning_rates(self, extent: float) -> dict[str, float]:
        """Initial learning rate per parameter (positions relative to the scene extent)."""
        return {"means": self.position_lr_init * extent, "sh_dc": self.feature_lr, "sh_rest": self.feature_rest_lr,
                "opacities": self.opacity_lr, "scales": self.scaling_lr, "quats": self.rotation_lr}

    def sh_degree_at(self, iteration: int) -> int:
        """Active SH degree at an iteration of the whole run: one more every `sh_interval`
        reference iterations, scaled like the other schedules (to the whole run's count)."""
        every = max(1, round(self.sh_interval * sum(self.iterations) / self.reference_iterations))
        return min(self.sh_degree, iteration // every)

    def stage_schedule(self, stage: int) -> dict[str, int]:
        """Iteration schedule of one stage: the reference schedule times iterations/30000, with
        floors on the densification and opacity-reset intervals (a too-short interval would
        leave no time to average gradients or to recover from a reset)."""
        n = self.iterations[stage]
        f = n / self.reference_iterations
        every = max(self.min_densify_every, round(self.densify_every * f))
        return dict(
            iterations=n,
            densify_every=every,
            densify_from=max(every, round(self.densify_from * f)),
            densify_until=round(self.densify_until * f),
            opacity_reset_every=max(self.min_opacity_reset_every, round(self.opacity_reset_every * f)),
        )


def stage_heights(height: int, profile: tuple[int, ...]) -> tuple[int, ...]:
    """Stage heights with the last at `height` and the earlier ones in `profile`'s proportions."""
    if height <= 0:
        raise ValueError(f"the last stage's image height must be positive, got {height}")
    return tuple(max(1, round(height * r / profile[-1])) for r in profile)


def configure(profile: str = "default", *, resolutions=None, image_height: int | None = None, iterations=None,
              none: tuple[str, ...] = (), **fields) -> TrainConfig:
    """The configuration `gvae train` and Blender's New from Photos ask for: a profile with the
    stage heights given (`resolutions`) or the last one (`image_height`, the others in the profile's
    proportions); `iterations` (one count, or one per stage) fixes the counts (no training on to
    convergence, unless `converge` is given too: then the last count is its planned one); with
    other heights and no iterations, the profile's counts where they fit, else its last count for
    every stage. Other `fields` override the profile's (None: the profile's);
    the fields named in `none` are set to None (a budget or cap of none)."""
    base = TrainConfig.profile(profile)
    if image_height is not None:
        resolutions = stage_heights(int(image_height), base.resolutions)
    values = {k: v for k, v in fields.items() if v is not None}
    if resolutions is not None:
        values["resolutions"] = tuple(int(r) for r in resolutions)
    n = len(values.get("resolutions", base.resolutions))
    if iterations is not None:
        its = tuple(int(i) for i in np.atleast_1d(iterations))
        its = its * n if len(its) == 1 else its
        if len(its) != n:
            raise ValueError(f"iterations: needs 1 or {n} numbers, got {len(its)}")
        values["iterations"] = its
        values.setdefault("converge", False)  # the counts asked for, unless training on is asked for too
    elif resolutions is not None and len(base.iterations) != n:
        values["iterations"] = (base.iterations[-1],) * n
    config = TrainConfig.profile(profile, **values)
    return dataclasses.replace(config, **dict.fromkeys(none)) if none else config


def position_lr(config: TrainConfig, extent: float, step: int, total: int) -> float:
    """Exponential (log-linear) decay from position_lr_init to position_lr_final, times extent."""
    t = min(max(step / max(total, 1), 0.0), 1.0)
    lr0, lr1 = config.position_lr_init, config.position_lr_final
    return extent * math.exp((1 - t) * math.log(lr0) + t * math.log(lr1))
