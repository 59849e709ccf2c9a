"""The cameras a splat file's training left beside it, for the commands that score a cloud from
views (compaction) when no capture is given: the capture's own cameras look where the photos did,
placed views can only guess (which costs more on the photos held out: docs/benchmarks/compact.md).

Where they are looked for, the first found wins:
- the reference 3DGS's model folder: `cameras.json` beside the splat or up to two folders above it
  (`MODEL/point_cloud/iteration_N/point_cloud.ply`), `capture.gs_cameras`;
- a `gvae train` run folder: its `run.json` names the capture (`data`) and the images it held out
  (`config.test_every`), whose training cameras are read (`load_cameras`).
Unreadable or stale files (a capture moved away) are passed over with the reason.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ..camera import Camera
from ..cloud import GaussianCloud
from ..datasets import DatasetError
from .dataset import read_capture
from .gs_cameras import GS_CAMERAS, read_gs_cameras
from .views import in_view

__all__ = ["FoundCameras", "cameras_beside", "training_cameras", "FOUND_MIN_SEEN"]

#: How many folders above a splat file a `cameras.json` is looked for (the reference's layout: 2).
LEVELS = 2
#: Cameras found beside a splat are used when together they have at least this share of its
#: Gaussians in view (fewer: they belong to another scene or frame, or the splat was moved).
FOUND_MIN_SEEN = 0.5


@dataclass
class FoundCameras:
    """Cameras found beside a splat file: `cameras` (the training ones), the capture or file they
    came from (`source`) and what they are (`how`: one line for the log)."""

    cameras: list[Camera]
    source: Path
    how: str


def cameras_beside(splat) -> tuple[FoundCameras | None, list[str]]:
    """(the training cameras found beside the splat file `splat`, or None; the files passed over,
    each with why). See the module docstring for where they are looked for."""
    path = Path(splat).resolve()
    passed: list[str] = []
    for folder in path.parents[:LEVELS + 1]:
        candidate = folder / GS_CAMERAS
        if candidate.is_file():
            try:  # (read once: a file of another kind is passed over with what is wrong with it)
                cams = read_gs_cameras(candidate).cameras
            except (DatasetError, OSError) as exc:
                passed.append(str(exc))
                continue
            return FoundCameras(cams, candidate, f"{len(cams)} training cameras from {candidate} (the reference "
                                "3DGS's output)"), passed
    run = path.parent / "run.json"
    if run.is_file():
        found = _run_cameras(run, passed)
        if found is not None:
            return found, passed
    return None, passed


def _run_cameras(run: Path, passed: list[str]) -> FoundCameras | None:
    """The training cameras of the capture a `gvae train` run (`run.json`) names, as it held them out."""
    try:
        meta = json.loads(run.read_text(encoding="utf-8"))
        data, every = meta["data"], meta.get("config", {}).get("test_every")
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        passed.append(f"{run}: no capture named (not a gvae train run)")
        return None
    capture = Path(data)
    if not capture.is_absolute() and not capture.exists():  # (recorded as given: relative to where it ran)
        capture = run.parent / capture
    try:
        cams = read_capture(capture, every, images=False).split_cameras("train")
    except (DatasetError, ValueError, OSError) as exc:
        passed.append(f"{run}: its capture {data} cannot be read: {exc}")
        return None
    return FoundCameras(cams, capture, f"{len(cams)} training cameras of {capture} (the capture {run} was trained "
                        "from" + (f", 1 in {every} held out" if every else "") + ")")


def training_cameras(splat, cloud: GaussianCloud) -> tuple[list[Camera] | None, list[str]]:
    """(the training cameras found beside the splat file `splat` (`cameras_beside`) when together
    they see FOUND_MIN_SEEN of `cloud`, the Gaussians read from it, else None; lines that say which
    cameras, or why none: the files passed over, cameras that do not see it)."""
    found, lines = cameras_beside(splat)
    if found is None:
        return None, lines
    sees = in_view(found.cameras, cloud)
    seen = float(sees.any(0).mean()) if sees.shape[1] else 0.0
    if seen < FOUND_MIN_SEEN:
        return None, lines + [f"found {found.how}, but they see {seen:.0%} of {splat} (moved, or another scene?): "
                              "views placed around it instead"]
    return found.cameras, lines + [f"scoring from {found.how}"]
