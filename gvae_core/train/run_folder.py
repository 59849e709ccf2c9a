"""The run folder a training writes: one class reads and writes all of it.

- `stage_<s>.ply`: each finished stage's cloud (with `gvae_id`, `gvae_parent` and its
  anti-aliasing size), `lineage.npz` (the stages' snapshots), `log.json` (one entry per stage);
- `run.json`: {"format", "config", "stages_done", "next_id", "data"}: what resumes it;
- `adam.npz`: Adam's state at the end of the last finished stage (when the configuration carries
  it from a stage to the next), so that a resumed run goes on as an uninterrupted one does;
- `stage_<s>_more_<n>.ply` and `more.json`: `gvae train RUN --more N`.

`RUN_FORMAT` is the version of run.json. Format 1 (no "format" key) left out the configuration
fields that were still at the values it trained with (`FORMAT_1_LEFT_OUT`); such runs resume.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_write, atomic_write_text
from ..cloud import GaussianCloud
from ..lineage import Lineage
from ..ply import read_ply, write_ply
from .config import TrainConfig

__all__ = ["RunFolder", "RunState", "RUN_FORMAT", "FORMAT_1_LEFT_OUT"]

RUN_FORMAT = 2
#: The configuration fields a format-1 run.json leaves out when they had these values.
FORMAT_1_LEFT_OUT: dict[str, Any] = {
    "antialias": "classic", "test_every": None, "validation_views": 0, "converge": False, "max_iterations": 30_000,
    "validation_every": 100, "patience": 600, "min_gain": 0.05, "max_minutes": None, "gaussians_per_pixel": None,
    "lr_schedule": "stage", "carry_optimizer": False, "opacity_resets": True, "average": None, "cool_down": 0,
}


@dataclass
class RunState:
    """What run.json says: the configuration, how many stages are finished, the next lineage id,
    and what the run was trained from (a capture's path; None: views in memory)."""

    config: TrainConfig
    stages_done: int
    next_id: int
    data: str | None


class RunFolder:
    """The files of one training run (module docstring) in `path`."""

    def __init__(self, path):
        self.path = Path(path)

    def file(self, name: str) -> Path:
        return self.path / name

    def stage_path(self, stage: int) -> Path:
        return self.path / f"stage_{stage}.ply"

    # ------------------------------------------------------------------ reading
    def state(self) -> RunState | None:
        """run.json's state; None when there is none; a broken one is an error naming it."""
        path = self.file("run.json")
        if not path.is_file():
            return None
        try:
            run = json.loads(path.read_text(encoding="utf-8"))
            saved = run["config"]
            if int(run.get("format", 1)) == 1:
                saved = {**FORMAT_1_LEFT_OUT, **saved}
            return RunState(TrainConfig.from_dict(saved), int(run["stages_done"]), int(run["next_id"]),
                            run.get("data"))
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: not a training run state file ({exc})") from None

    def finished(self) -> RunState:
        """The state of a run with at least one finished stage (for `train_more`); else an error."""
        state = self.state()
        if state is None:
            raise ValueError(f"{self.path}: not a training run (no run.json)")
        return state

    def resume(self, config: TrainConfig) -> tuple[Lineage, list[dict], int] | None:
        """(lineage, log, next_id) of the finished stages of a run of `config` here, or None (no
        run, or none finished). A run of another configuration is an error."""
        state = self.state()
        if state is None:
            return None
        if state.config != config:
            saved, asked = state.config.to_dict(), config.to_dict()
            diff = sorted(k for k in asked if saved.get(k) != asked[k])
            raise ValueError(f"{self.path}: holds a run with a different configuration ({', '.join(diff)}); "
                             "use another output directory or resume=False")
        if state.stages_done == 0:
            return None
        lineage = Lineage.load(self.file("lineage.npz"))
        log = self.log()
        done = state.stages_done
        if lineage.n_stages < done or len(log) < done:
            raise ValueError(f"{self.path}: run.json says {done} stage(s) are done but lineage.npz has "
                             f"{lineage.n_stages} and log.json {len(log)}")
        kept = Lineage(lineage.center, lineage.scale)  # (the normalisation it was saved with)
        for s in range(done):
            snap = lineage.snapshots[s]
            kept.add_stage(snap.cloud, snap.ids, snap.parents, lineage.resolutions[s])
        return kept, log[:done], state.next_id

    def log(self) -> list[dict]:
        """log.json's entries (one per finished stage); none without it."""
        path = self.file("log.json")
        return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else []

    def adam(self) -> dict[str, np.ndarray] | None:
        """Adam's state at the end of the last finished stage, when it was kept."""
        path = self.file("adam.npz")
        if not path.is_file():
            return None
        with np.load(path) as z:
            return dict(z)

    def stage_size(self, stage: int, key: str, count: int) -> np.ndarray | None:
        """The anti-aliasing size `key` a finished stage's PLY stores, if it is there for `count` Gaussians."""
        path = self.stage_path(stage)
        if not path.is_file():
            return None
        saved = read_ply(path)
        return np.asarray(saved.extra[key], np.float32) if key in saved.extra and len(saved) == count else None

    # ------------------------------------------------------------------ writing
    def start(self, restart: bool) -> None:
        """Make the folder; with `restart`, forget a run that is there (its files are overwritten)."""
        self.path.mkdir(parents=True, exist_ok=True)
        if restart and self.file("run.json").exists():
            self.file("run.json").unlink()

    def save_stage(self, stage: int, cloud: GaussianCloud, lineage: Lineage, log: list[dict], config: TrainConfig,
                   next_id: int, data: str | None, adam: dict[str, np.ndarray] | None) -> Path:
        """A finished stage: its PLY, Adam's state (when carried), the lineage, the log and run.json
        last (what resumes)."""
        path = write_ply(cloud, self.stage_path(stage))
        if adam is not None:
            atomic_write(self.file("adam.npz"), lambda f: np.savez(f, **adam))
        lineage.save(self.file("lineage.npz"))
        self._write_json("log.json", log)
        self._write_json("run.json", {"format": RUN_FORMAT, "config": config.to_dict(), "stages_done": stage + 1,
                                      "next_id": next_id, "data": data})
        return path

    def save_more(self, stage: int, iterations: int, cloud: GaussianCloud, entry: dict) -> Path:
        """A stage trained `iterations` more: stage_<s>_more_<n>.ply and its entry in more.json."""
        path = write_ply(cloud, self.path / f"stage_{stage}_more_{int(iterations)}.ply")
        entry = {**entry, "file": path.name}
        more = self.file("more.json")
        entries = json.loads(more.read_text(encoding="utf-8")) if more.is_file() else []
        self._write_json("more.json", [e for e in entries if e.get("file") != path.name] + [entry])
        return path

    def _write_json(self, name: str, obj) -> None:
        atomic_write_text(self.file(name), json.dumps(obj, indent=2))
