"""`compact(tolerance=...)`: the fewest Gaussians whose compaction keeps the picture, at the
training sampling rate, at or above a PSNR against the input's own render."""

from __future__ import annotations

import math

from .finetune import training_rate
from .merge import merge_groups
from .removal import removal_groups
from .report import input_images, report_psnr


def tolerance_count(src, scores, tolerance: float, cameras, cams, how: dict, settings, say) -> int:
    """The fewest Gaussians (to within 1% of the input's count) whose compaction keeps the
    picture at the training sampling rate at or above `tolerance` dB against the input's: a
    bisection on the count (the scoring views `cams` rescaled by `finetune.training_rate`;
    `how`: `removal_groups`' arguments)."""
    check = training_rate(src, cameras, cams)
    reference = input_images(src, check, settings)
    n = len(src)

    def good(target: int) -> float:
        groups = removal_groups(src, scores, target, **how)
        return report_psnr(reference, merge_groups(src, groups)[0], check, settings)

    lo, hi = 0, n  # good(hi) holds (the input itself); find the smallest count that holds
    step = 0
    while hi - lo > max(1, n // 100):
        mid = int(round(math.sqrt(max(lo, 1) * hi))) if lo == 0 or hi / max(lo, 1) > 4 else (lo + hi) // 2
        mid = min(max(mid, lo + 1), hi - 1)
        step += 1
        value = good(mid)
        say(0.1 + 0.5 * min(step / 12, 1.0), f"tolerance: {mid:,} Gaussians give {value:.2f} dB")
        if value >= tolerance:
            hi = mid
        else:
            lo = mid
    return hi
