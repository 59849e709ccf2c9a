"""`gvae report`: the experiment's results as tables, plots and plain statements
(reports/README.md, results.json, PNGs), all computed from the document that
`gvae_core.experiment.run_experiment` returns.

Every number about a method is a mean over (scene, seed) pairs with its 95% interval (Student t);
geometry is compared relative to the unrefined cloud of the same pair (% change), images as
differences (dB). The headline compares `refine`'s default (the detail model) with what costs the
same (the unrefined cloud, the global knob per octave, linear lineage extrapolation) and shows the
oracle's bound beside it; the paper's method (Ours-∇², the lineage VAEs) is compared at each step
with the best alternative at the same Gaussian count for that pair and metric: the controls
(split, random selection with the model, duplicate-in-place) and, with fewer Gaussians, the
unrefined cloud.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path

import numpy as np
from scipy import stats

from .atomic import atomic_write_text
from .experiment import (BASELINE, CONTROLS, DEFAULT, DUPLICATE, EXTRAPOLATION, FINETUNE, FOUR_X, IMAGES,
                         IMAGES_CHILDREN, IMAGES_NO_CHILDREN, KNOB, ORACLE, ORACLE_IMAGES, OURS, OURS_H, RANDOM, REAL,
                         SPLIT, json_safe)

METHOD_NAMES = {BASELINE: "3DGS, unrefined", KNOB: "global scale knob per octave", REAL: "3DGS on the real images",
                OURS: "Ours (every Gaussian)", OURS_H: "Ours-∇²", SPLIT: "plain split", RANDOM: "random + model",
                DUPLICATE: "duplicate in place", DEFAULT: "refine default (detail model + fidelity check)",
                EXTRAPOLATION: "linear lineage extrapolation", ORACLE: "oracle (upper bound)",
                IMAGES: "refine with the images", IMAGES_NO_CHILDREN: "refine with the images, no children",
                IMAGES_CHILDREN: "refine with the images, with children",
                FINETUNE: "the same steps of plain 1x training", ORACLE_IMAGES: "the same fit to the real 2x images "
                "(oracle)"}
METHOD_NAMES.update({FOUR_X[BASELINE]: "3DGS, unrefined", FOUR_X[DEFAULT]: "refine default (detail model)",
                     FOUR_X[IMAGES]: "refine with the images", FOUR_X[FINETUNE]: "the same steps of plain 1x training",
                     FOUR_X[REAL]: "3DGS on the real 4x images"})
#: Refine with the images: every pair at least this much above the unrefined cloud at 2x (its goal).
IMAGES_FLOOR_DB = 0.3
#: What costs the same as refine's default (no Gaussian added): it must beat each of them.
SAME_COST = (BASELINE, KNOB, EXTRAPOLATION)
#: The default's table: (row key, label, digits).
DEFAULT_METRICS = (("psnr_2x", "PSNR 2x dB", 2), ("psnr_1.5x", "PSNR 1.5x dB", 2), ("psnr_1x", "PSNR 1x dB", 2),
                   ("ssim_2x", "SSIM 2x", 4))
#: A pair where the default loses more than this (dB at 2x) to the unrefined cloud is listed.
LOSS_MARGIN_DB = 0.1
#: (row key, label, lower is better, relative to the unrefined cloud in %)
METRICS = (("chamfer", "Chamfer", True, True), ("weighted_accuracy", "weighted accuracy", True, True),
           ("psnr_2x", "PSNR 2x", False, False), ("ssim_2x", "SSIM 2x", False, False))
#: What Ours-∇² is compared with at each step: the controls at its count, and the cheaper baseline.
ALTERNATIVES = (*CONTROLS, BASELINE)


def _nanmean(values) -> float:
    """Mean of the finite values; NaN (without numpy's warning) when there are none."""
    a = np.asarray(values, np.float64)
    a = a[np.isfinite(a)]
    return float(a.mean()) if len(a) else float("nan")


def mean_ci(values) -> tuple[float, float]:
    """Mean and the half-width of its 95% interval (Student t); NaN values are left out."""
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], np.float64)
    if len(v) == 0:
        return float("nan"), float("nan")
    if len(v) == 1:
        return float(v[0]), float("nan")
    return float(v.mean()), float(stats.t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v)))


def _fmt(m: float, h: float | None = None, digits: int = 2, sign: bool = False) -> str:
    if m is None or not math.isfinite(m):
        return "–"
    s = f"{m:+.{digits}f}" if sign else f"{m:.{digits}f}"
    return s if h is None or not math.isfinite(h) else f"{s} ± {h:.{digits}f}"


class Results:
    """Lookup over the rows of one split: value(scene, seed, method, step, key)."""

    def __init__(self, doc: dict, split: str = "test"):
        self.doc = doc
        self.rows = [r for r in doc["rows"] if split in (r.get("split"), "mixed") and r["method"] != "render"]
        self.index = {(r["scene"], r["seed"], r["method"], r.get("step", 0), r.get("scale")): r for r in self.rows}
        self.pairs = sorted({(r["scene"], r["seed"]) for r in self.rows})
        self.scenes = sorted({s for s, _ in self.pairs})
        self.steps = range(1, doc["protocol"]["steps"] + 1)

    def row(self, scene, seed, method, step=0, scale=None) -> dict | None:
        return self.index.get((scene, seed, method, step, scale))

    def value(self, scene, seed, method, step, key, scale=None) -> float:
        r = self.row(scene, seed, method, step, scale)
        v = None if r is None else r.get(key)
        return float("nan") if v is None else float(v)

    def change(self, scene, seed, method, step, key, relative: bool, scale=None, base_method: str = BASELINE) -> float:
        """The metric's change against the unrefined cloud of the pair (% when relative)."""
        base = self.value(scene, seed, base_method, 0, key)
        v = self.value(scene, seed, method, step, key, scale)
        if relative:
            return 100.0 * (v - base) / base if base else float("nan")
        return v - base

    def best_alternative(self, scene, seed, step, key, lower: bool, relative: bool) -> tuple[str, float]:
        """The best alternative to Ours-∇² at `step` for one pair and metric, and its change."""
        options = [(m, self.change(scene, seed, m, step if m in CONTROLS else 0, key, relative)) for m in ALTERNATIVES]
        options = [(m, v) for m, v in options if math.isfinite(v)]
        if not options:
            return "–", float("nan")
        return (min if lower else max)(options, key=lambda mv: mv[1])


def default_table(res: Results) -> list[str]:
    """refine's default, what costs the same and the oracle: mean ± 95% interval of the change
    against the unrefined cloud; then the default against the best of the same-cost alternatives
    per pair, and the pairs where it is better."""
    methods = (DEFAULT, KNOB, EXTRAPOLATION, ORACLE)
    lines = ["| metric | " + " | ".join(METHOD_NAMES[m] for m in methods)
             + " | default − best same-cost alternative | default better in |", "|---|" + "---|" * (len(methods) + 2)]
    for key, label, digits in DEFAULT_METRICS:
        cells = [_fmt(*mean_ci([res.change(s, d, m, 1, key, False) for s, d in res.pairs]), digits, True)
                 for m in methods]
        diff, wins = [], 0
        for scene, seed in res.pairs:
            o = res.change(scene, seed, DEFAULT, 1, key, False)
            alts = [res.change(scene, seed, m, 0 if m == BASELINE else 1, key, False) for m in SAME_COST]
            alts = [a for a in alts if math.isfinite(a)]
            if math.isfinite(o) and alts:
                diff.append(o - max(alts))
                wins += o > max(alts)
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {_fmt(*mean_ci(diff), digits, True)} | "
                     f"{wins}/{len(diff)} |")
    return lines


def default_losses(res: Results) -> list[str]:
    """Every pair where the default is below the unrefined cloud by more than LOSS_MARGIN_DB at 2x,
    or below the extrapolation control or the knob at 2x."""
    out = []
    for scene, seed in res.pairs:
        o = res.change(scene, seed, DEFAULT, 1, "psnr_2x", False)
        worse = []
        if o < -LOSS_MARGIN_DB:
            worse.append(f"{o:+.2f} dB against the unrefined cloud")
        for m in (KNOB, EXTRAPOLATION):
            a = res.change(scene, seed, m, 1, "psnr_2x", False)
            if math.isfinite(o) and math.isfinite(a) and o < a:
                worse.append(f"{o - a:+.2f} dB against {METHOD_NAMES[m]}")
        if worse:
            out.append(f"- {scene}, seed {seed}: PSNR 2x " + "; ".join(worse))
    return out or [f"- nowhere: the default is within {LOSS_MARGIN_DB} dB of the unrefined cloud or above it, and "
                   f"at least as good as the knob and the extrapolation, on every pair."]


def _with_and_without_children(res: Results, scene, seed) -> tuple[str, str] | None:
    """The pair's fit with children and the same without them: the default and its other row."""
    if res.row(scene, seed, IMAGES_CHILDREN, 1):
        return IMAGES_CHILDREN, IMAGES
    if res.row(scene, seed, IMAGES_NO_CHILDREN, 1):
        return IMAGES, IMAGES_NO_CHILDREN
    return None


def images_table(res: Results) -> list[str]:
    """Refine with the images against what it is measured by: mean ± 95% interval of the change
    against the unrefined cloud per metric, then per pair at 2x with the Gaussians its children add."""
    methods = [m for m in (IMAGES, IMAGES_CHILDREN, IMAGES_NO_CHILDREN, DEFAULT, EXTRAPOLATION, FINETUNE,
                           ORACLE_IMAGES) if any(res.row(s, d, m, 1) for s, d in res.pairs)]
    if IMAGES not in methods:
        return []
    lines = ["| metric | " + " | ".join(METHOD_NAMES[m] for m in methods) + " | 3DGS on the real 2x images |",
             "|---|" + "---|" * (len(methods) + 1)]
    for key, label, digits in DEFAULT_METRICS:
        cells = [_fmt(*mean_ci([res.change(s, d, m, 1, key, False) for s, d in res.pairs]), digits, True)
                 for m in methods]
        real = _fmt(*mean_ci([res.change(s, d, REAL, 0, key, False, "2x") for s, d in res.pairs]), digits, True)
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {real} |")
    added = {m: _nanmean([res.value(s, d, m, 1, "added") for s, d in res.pairs]) for m in methods}
    lines.append("| Gaussians added | " + " | ".join(f"{added[m]:.0f}" if math.isfinite(added[m]) else "0"
                                                      for m in methods) + " | – |")
    other = next((m for m in (IMAGES_CHILDREN, IMAGES_NO_CHILDREN) if m in methods), None)
    lines += ["", "Per pair, PSNR change at 2x (dB); the gain per 1,000 added Gaussians is what the fit with children "
              "gains over the same fit without them:", "",
              "| scene | seed | with the images | " + (METHOD_NAMES[other].split(", ")[-1] if other else "–")
              + " | detail model | 1x training | oracle | added | gain per 1,000 added |",
              "|---|---|---|---|---|---|---|---|---|"]
    for s, d in res.pairs:
        g = {m: res.change(s, d, m, 1, "psnr_2x", False) for m in (IMAGES, other, DEFAULT, FINETUNE, ORACLE_IMAGES)}
        kids = _with_and_without_children(res, s, d)
        n = res.value(s, d, kids[0], 1, "added") if kids else float("nan")
        per = (1000.0 * (g[kids[0]] - g[kids[1]]) / n if kids and n and math.isfinite(n) else float("nan"))
        lines.append(f"| {s} | {d} | " + " | ".join(_fmt(g[m], digits=2, sign=True) for m in g)
                     + f" | {n:.0f} | {_fmt(per, digits=2, sign=True)} |")
    return lines


def images_goals(res: Results) -> list[str]:
    """The goals of refine with the images, each met or not, in words."""
    gain = [res.change(s, d, IMAGES, 1, "psnr_2x", False) for s, d in res.pairs]
    over = [g - res.change(s, d, FINETUNE, 1, "psnr_2x", False) for g, (s, d) in zip(gain, res.pairs)]
    one = [res.change(s, d, IMAGES, 1, "psnr_1x", False) for s, d in res.pairs]
    if not any(math.isfinite(g) for g in gain):
        return []
    low = [f"{s} s{d} ({g:+.2f})" for g, (s, d) in zip(gain, res.pairs) if g < IMAGES_FLOOR_DB]
    m, h = mean_ci(gain)
    mo, ho = mean_ci(over)
    return [f"- PSNR at 2x: {_fmt(m, h, 2, True)} dB over the unrefined cloud (goal +1.0: "
            f"{'met' if m >= 1.0 else 'not met'}); lowest pair {min(gain):+.2f} dB (goal: every pair "
            f"+{IMAGES_FLOOR_DB:g} or more: {'met' if not low else 'not met: ' + ', '.join(low)}).",
            f"- Above the same number of plain 1x training steps: {_fmt(mo, ho, 2, True)} dB (goal +0.7: "
            f"{'met' if mo >= 0.7 else 'not met'}); worst pair {min(over):+.2f}.",
            f"- PSNR at 1x: largest change {max(abs(v) for v in one):.4f} dB (goal within 0.01: "
            f"{'met' if max(abs(v) for v in one) <= 0.01 else 'not met'})."]


def four_x_table(res: Results) -> list[str]:
    """From the first training stage two octaves up: change against its unrefined cloud at 2x and 4x."""
    methods = [m for m in (FOUR_X[IMAGES], FOUR_X[DEFAULT], FOUR_X[FINETUNE], FOUR_X[REAL])
               if any(res.row(s, d, m, 0 if m == FOUR_X[REAL] else 2) for s, d in res.pairs)]
    if not methods:
        return []
    lines = ["| | " + " | ".join(METHOD_NAMES[m] for m in methods) + " |", "|---|" + "---|" * len(methods)]
    for key, label in (("psnr_4x", "PSNR 4x dB"), ("psnr_2x", "PSNR 2x dB"), ("psnr_1x", "PSNR 1x dB"),
                       ("ssim_4x", "SSIM 4x")):
        digits = 4 if key.startswith("ssim") else 2
        cells = [_fmt(*mean_ci([res.change(s, d, m, 0 if m == FOUR_X[REAL] else 2, key, False,
                                           base_method=FOUR_X[BASELINE]) for s, d in res.pairs]), digits, True)
                 for m in methods]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def fault_table(doc: dict) -> list[str]:
    """Refine with the images on captures with simulated faults: the change at 2x against the
    unrefined cloud trained on the same faulted images, with each guard off and on."""
    rows = doc.get("fault_rows") or []
    if not rows:
        return []
    faults = list(dict.fromkeys(r["fault"] for r in rows))
    guards = list(dict.fromkeys(r["guard"] for r in rows if r["method"] == IMAGES))
    base = {(r["scene"], r["seed"], r["fault"]): r for r in rows if r["method"] == BASELINE}
    lines = ["| fault | pairs | unrefined PSNR 2x | " + " | ".join(f"guard: {g}" for g in guards) + " | lowest pair |",
             "|---|---|---|" + "---|" * (len(guards) + 1)]
    for fault in faults:
        cells, lowest = [], []
        keys = [k for k in base if k[2] == fault]
        for guard in guards:
            gains = [r["psnr_2x"] - base[(r["scene"], r["seed"], fault)]["psnr_2x"] for r in rows
                     if r["fault"] == fault and r["guard"] == guard and r["method"] == IMAGES]
            cells.append(_fmt(*mean_ci(gains), 2, True))
            lowest += gains
        lines.append(f"| {fault} | {len(keys)} | {_nanmean([base[k]['psnr_2x'] for k in keys]):.2f} | "
                     + " | ".join(cells) + f" | {min(lowest):+.2f} |")
    return lines


def headline_table(res: Results) -> list[str]:
    """Ours-∇² against the best alternative at the same count, per step and metric."""
    lines = ["| step | metric | Ours-∇² | best alternative (most often) | Ours-∇² − best | Ours-∇² better in |",
             "|---|---|---|---|---|---|"]
    for k in res.steps:
        for key, label, lower, relative in METRICS:
            ours, best, diff, names, wins = [], [], [], Counter(), 0
            for scene, seed in res.pairs:
                o = res.change(scene, seed, OURS_H, k, key, relative)
                name, b = res.best_alternative(scene, seed, k, key, lower, relative)
                if not (math.isfinite(o) and math.isfinite(b)):
                    continue
                ours.append(o)
                best.append(b)
                diff.append(o - b)
                names[name] += 1
                wins += (o < b) if lower else (o > b)
            unit = "%" if relative else ("dB" if key.startswith("psnr") else "")
            digits = 4 if key.startswith("ssim") else 2
            common = METHOD_NAMES.get(names.most_common(1)[0][0], "–") if names else "–"
            lines.append(f"| +{k} | {label} ({unit or 'change'}, {'lower' if lower else 'higher'} is better) | "
                         f"{_fmt(*mean_ci(ours), digits, True)} | {_fmt(*mean_ci(best), digits, True)} ({common}) | "
                         f"{_fmt(*mean_ci(diff), digits, True)} | {wins}/{len(diff)} |")
    return lines


def methods_table(res: Results) -> list[str]:
    """Every method and step: mean ± 95% interval of the change against the unrefined cloud."""
    head = ["method", "step", "Gaussians", "Chamfer %", "accuracy %", "weighted acc. %", "completeness %",
            "PSNR 1x dB", "PSNR 2x dB", "PSNR 2x classic dB", "SSIM 2x"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    cells = [("chamfer", True, 2), ("accuracy", True, 2), ("weighted_accuracy", True, 2), ("completeness", True, 2),
             ("psnr_1x", False, 2), ("psnr_2x", False, 2), ("psnr_2x_classic", False, 2), ("ssim_2x", False, 4)]
    entries = [(BASELINE, 0, None), (REAL, 0, "1.5x"), (REAL, 0, "2x")]
    entries += [(m, 1, None) for m in (DEFAULT, KNOB, EXTRAPOLATION, ORACLE)]
    entries += [(m, k, None) for m in (OURS, OURS_H, *CONTROLS) for k in res.steps]
    for method, step, scale in entries:
        counts = [res.value(s, d, method, step, "n_gaussians", scale) for s, d in res.pairs]
        if not any(math.isfinite(c) for c in counts):
            continue
        row = [METHOD_NAMES[method] + (f" {scale}" if scale else ""), f"+{step}" if step else "–",
               f"{_nanmean(counts):.0f}"]
        for key, relative, digits in cells:
            row.append(_fmt(*mean_ci([res.change(s, d, method, step, key, relative, scale) for s, d in res.pairs]),
                            digits, True))
        lines.append("| " + " | ".join(row) + " |")
    return lines


def scene_table(res: Results) -> list[str]:
    """PSNR at 2x per scene (mean over seeds) for the baselines and every method at +1."""
    cols = [(BASELINE, 0, None, "psnr_2x_classic", "3DGS classic"), (BASELINE, 0, None, "psnr_2x", "3DGS"),
            (REAL, 0, "2x", "psnr_2x", "3DGS real 2x")]
    cols += [(m, 1, None, "psnr_2x", METHOD_NAMES[m]) for m in (DEFAULT, KNOB, EXTRAPOLATION, ORACLE)]
    cols += [(m, 1, None, "psnr_2x", f"{METHOD_NAMES[m]} +1") for m in (OURS, OURS_H, *CONTROLS)]
    lines = ["| scene | " + " | ".join(c[-1] for c in cols) + " |", "|" + "---|" * (len(cols) + 1)]
    for scene in res.scenes:
        seeds = [d for s, d in res.pairs if s == scene]
        vals = [_nanmean([res.value(scene, d, m, k, key, scale) for d in seeds]) for m, k, scale, key, _ in cols]
        lines.append(f"| {scene} | " + " | ".join(_fmt(v) for v in vals) + " |")
    return lines


def losses(res: Results) -> list[str]:
    """Every (scene, seed, step) where Ours-∇² is worse than the best alternative, with the
    metrics and margins."""
    out = []
    for scene, seed in res.pairs:
        for k in res.steps:
            worse = []
            for key, label, lower, relative in METRICS:
                o = res.change(scene, seed, OURS_H, k, key, relative)
                name, b = res.best_alternative(scene, seed, k, key, lower, relative)
                if math.isfinite(o) and math.isfinite(b) and ((o > b) if lower else (o < b)):
                    unit = " points" if relative else (" dB" if key.startswith("psnr") else "")
                    worse.append(f"{label} {o - b:+.{4 if 'ssim' in key else 2}f}{unit} against {METHOD_NAMES[name]}")
            if worse:
                out.append(f"- {scene}, seed {seed}, +{k}: " + "; ".join(worse))
    return out or ["- nowhere: Ours-∇² is at least as good as the best alternative on every pair, step and metric."]


def plots(doc: dict, res: Results, out: Path) -> list[str]:
    """Chamfer and weighted accuracy against Gaussian count for every method (curves over the
    steps), and training time/memory of the runs; returns the file names."""
    import matplotlib  # noqa: PLC0415 - loaded only to draw, and told first to draw without a screen

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415 - after matplotlib.use

    names = []
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, (key, label) in zip(axes, (("chamfer", "Chamfer"), ("weighted_accuracy", "weighted accuracy"))):
        for method in (OURS, OURS_H, *CONTROLS):
            xs, ys = [1.0], [0.0]
            for k in res.steps:
                n = [res.value(s, d, method, k, "n_gaussians") / res.value(s, d, BASELINE, 0, "n_gaussians")
                     for s, d in res.pairs]
                xs.append(float(_nanmean(n)))
                ys.append(mean_ci([res.change(s, d, method, k, key, True) for s, d in res.pairs])[0])
            ax.plot(xs, ys, "o-", label=METHOD_NAMES[method])
        for scale in ("1.5x", "2x"):
            n = _nanmean([res.value(s, d, REAL, 0, "n_gaussians", scale)
                          / res.value(s, d, BASELINE, 0, "n_gaussians") for s, d in res.pairs])
            y = mean_ci([res.change(s, d, REAL, 0, key, True, scale) for s, d in res.pairs])[0]
            ax.plot([n], [y], "^", label=f"{METHOD_NAMES[REAL]} {scale}")
        ax.axhline(0, color="grey", lw=0.5)
        ax.set_xlabel("Gaussians / unrefined count")
        ax.set_ylabel(f"{label}, % change (lower is better)")
        ax.set_title(f"{label} against Gaussian count")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "geometry_vs_count.png", dpi=110)
    plt.close(fig)
    names.append("geometry_vs_count.png")

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for run in doc["runs"].values():
        log = run["log"]
        label = f"{run['scene']} s{run['seed']}"
        axes[0].plot(np.cumsum([e["seconds"] for e in log]), [e["test_psnr"] for e in log], "o-", label=label)
        axes[1].plot([e["resolution"] for e in log], [e["peak_rss_mb"] for e in log], "o-", label=label)
    axes[0].set_xlabel("cumulative training time, s (1 thread)")
    axes[0].set_ylabel("test PSNR at the stage's resolution, dB")
    axes[1].set_xlabel("training resolution, px")
    axes[1].set_ylabel("peak resident memory, MB")
    axes[1].legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(out / "training.png", dpi=110)
    plt.close(fig)
    names.append("training.png")
    return names


def knob_lines(doc: dict) -> list[str]:
    """How the global knob and the extrapolation factor were chosen."""
    out = []
    for key, what in (("knob", "One global scale factor per octave above each Gaussian's training rate"),
                      ("extrapolation", "Linear lineage extrapolation: the share of each Gaussian's last "
                       "stage-to-stage change of log-scales and opacity it continues, per octave")):
        tuned = doc.get(key)
        if not tuned:
            continue
        out += [f"{what}, chosen on the training scenes ({', '.join(tuned['scenes'])}) by the mean PSNR at 2x of "
                f"their unrefined clouds: **x{tuned['factor']:g}**.", "",
                "| factor | " + " | ".join(tuned["psnr_2x"]) + " |", "|---|" + "---|" * len(tuned["psnr_2x"]),
                "| mean PSNR 2x (train scenes) | " + " | ".join(_fmt(v) for v in tuned["psnr_2x"].values()) + " |",
                ""]
    return out


def _cached(doc: dict) -> int:
    """How many of the report's training runs were taken from the cache (trained in under 1 s)."""
    return sum(1 for r in doc["runs"].values() if r.get("seconds", {}).get("train", 0.0) < 1.0)


def write_report(doc: dict, out, *, command: str = "") -> Path:
    """results.json, README.md and the plots into `out`."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    doc = json_safe(doc)
    atomic_write_text(out / "results.json", json.dumps(doc, indent=1) + "\n")
    split = doc.get("split", "test")
    res = Results(doc, split)
    figures = plots(doc, res, out)
    p, model = doc["protocol"], doc["model"]
    detail = model.get("detail", {})
    md = [f"# GaussianVAE: experiment report ({p['name']} profile)", "",
          f"Made by `{command or 'gvae report'}` on {doc['started']}, in {doc['seconds'] / 60:.1f} min on this "
          f"machine (2 CPU cores, no GPU; {_cached(doc)} of the {len(doc['runs'])} training runs came from the "
          f"cache).", "",
          (f"**Scenes**: the test split ({', '.join(res.scenes)}), looked at only for this report; no choice of "
           f"any kind was made on them." if split == "test" else
           f"**Scenes**: the {split} split ({', '.join(res.scenes)}): where choices are made; the test split's "
           f"report is the one to quote.") + f" **Seeds**: {', '.join(map(str, p['seeds']))} (3DGS training and "
          f"refinement), so every mean is over {len(res.pairs)} (scene, seed) pairs, ± its 95% interval.", "",
          f"**Protocol**: progressive 3DGS with lineage at {', '.join(map(str, p['resolutions']))} px (training "
          f"resolution {p['resolutions'][-1]} px; scenes rendered by Blender at the `{p['scene_profile']}` "
          f"profile), continued with the real {', '.join(map(str, p['higher']))} px images (1.5x, 2x: the upper "
          f"bound). From the training-resolution stage and its lineage only: `refine`'s default, the detail "
          f"model's changes per octave above each Gaussian's training rate (`gvae_core.detail`, "
          f"`gvae_core.octaves`; no Gaussian added, the training-resolution picture kept by construction) with "
          f"the fidelity check, at the same cost as the global scale knob per octave and linear lineage "
          f"extrapolation (each with one factor chosen on the training scenes), and below the oracle, every "
          f"Gaussian's log-scale and opacity changes fitted to the pair's real 1.5x and 2x training views (an "
          f"upper bound, not a method). The paper's method, +1..+{p['steps']}: Ours refines every Gaussian with "
          f"the lineage VAEs, Ours-∇² those the Hessian budget `{p['budget']}` selects; controls at Ours-∇²'s "
          f"output count, step by step: the plain 3DGS split, random selection with the model (thinned to the "
          f"count), duplicate-in-place (copies sharing the opacity).", "",
          f"**Rendering**: images are scored with the `{p['antialias']}` anti-aliasing mode (every cloud carries "
          f"the anti-aliasing size of the cameras it was trained with, `gvae_core.antialias`); the classic "
          f"render (+0.3 px², which ignores the changes per octave) is beside it.", "",
          f"**Models**: detail model `{detail.get('dir', '?')}` ({detail.get('bytes', 0) / 1e3:.0f} kB float32, "
          f"trained on {', '.join(detail.get('meta', {}).get('train_scenes') or ['?'])}); lineage VAEs "
          f"`{model.get('dir')}`, geometry {model['sizes']['geometry'] / 1e6:.2f} MB + appearance "
          f"{model['sizes']['appearance'] / 1e6:.2f} MB (float32), trained on "
          f"{', '.join(model.get('train_scenes') or ['?'])}.", "",
          "**Metrics**: Chamfer = mean of accuracy (Gaussian centres to the ground-truth mesh) and completeness "
          "(visible mesh samples to the nearest centre); weighted accuracy weighs each centre by its opacity; "
          "geometry as % change against the unrefined cloud of the same pair (negative is better). PSNR/SSIM "
          "against the ground-truth test views, white background; NIQE of the 2x renders in results.json.", "",
          "## Refine with the capture's images (multi-view super-resolution)", "",
          "`refine(images=...)`: every Gaussian's changes per octave fitted so that the cloud drawn at twice the "
          "training resolution and area-averaged back down reproduces each training image; no 2D prior. Change "
          "against the unrefined cloud of the same pair (matched render), beside the detail model alone, linear "
          "lineage extrapolation, the same number of plain training steps at 1x (which also changes the 1x "
          "picture), the same fit to the real 2x training images (the oracle of its quantities) and 3DGS trained "
          "on the real 2x images.", "", *images_table(res), "", *images_goals(res), "",
          "### Four times the training resolution", "",
          "From the run's first stage (a quarter of the test views' resolution), two octaves up; change against "
          "that stage's unrefined cloud.", "", *four_x_table(res), "",
          "### Simulated capture faults", "",
          "Each pair trained again on faulted training images (`gvae_core.scenes.faults`: cameras turned by a "
          "random rotation that moves the image by the stated amount at the training resolution, exposure "
          "varying by up to 10% per image, images made with another filter than the area average), then refined "
          "from those images with each guard off and on; change at 2x against its own unrefined cloud.", "",
          *fault_table(doc), "",
          "## Headline: refine's default against what costs the same", "",
          "Change against the unrefined cloud (matched render) of the same pair; the last two columns compare "
          "the default with the best of the unrefined cloud, the knob and the extrapolation, pair by pair.", "",
          *default_table(res), "",
          "### Where the default loses", "", *default_losses(res), "",
          "## The paper's method: Ours-∇² against the best alternative at the same count", "",
          "Per pair and metric, the best of the controls at Ours-∇²'s count and of the (cheaper) unrefined "
          "cloud.", "", *headline_table(res), "",
          "## Every method", "", *methods_table(res), "",
          "## PSNR at 2x per test scene (mean over seeds)", "", *scene_table(res), "",
          "## Where Ours-∇² loses", "", *losses(res), "",
          "## The knob and the extrapolation factor", "", *knob_lines(doc), "## Plots", ""]
    md += [f"![{f}]({f})" for f in figures] + [""]
    (out / "README.md").write_text("\n".join(md))
    return out / "README.md"
