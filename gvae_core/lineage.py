"""Gaussian lineages: per-stage snapshots of a progressive 3DGS run, turned into VAE features.

Progressive training snapshots every live Gaussian at each stage boundary s = 0..S-1: its raw
parameters, a persistent `id` and a `parent`, the id of its nearest ancestor present at stage
s-1 (its own id if it was there itself, -1 at stage 0 or when it has no ancestor there). The
lineage of a Gaussian alive at stage k is the sequence of nodes 0..k: its own snapshot where it
existed (exist=1), else its nearest ancestor's (exist=0). Each node has two feature vectors
(DESIGN.md): geometry (11) and appearance (50), in a scene-normalised frame so that one model
serves every scene. numpy only; torch is never imported here.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import quaternions
from .atomic import atomic_write
from .cloud import EXTREME_LOG_SCALE, GaussianCloud
from .conventions import LOG_SCALE_RANGE, OPACITY_LOGIT_RANGE, SH_REST_COUNTS

GEOMETRY_DIM = 11
APPEARANCE_DIM = 50
#: Column slices of the feature vectors.
GEO_POSITION, GEO_QUAT, GEO_LOG_SCALE, GEO_EXIST = slice(0, 3), slice(3, 7), slice(7, 10), 10
APP_SH_REST, APP_SH_DC, APP_OPACITY, APP_EXIST = slice(0, 45), slice(45, 48), 48, 49
#: `cloud_from_features(bounded=True)` keeps SH coefficients within +-BOUNDED_SH.
BOUNDED_SH = 1e3

_FORMAT = "gvae-lineage-1"
_PARAMS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")


# ------------------------------------------------------------------ features

def geometry_features(cloud: GaussianCloud, center, scale: float, exist: float = 1.0) -> np.ndarray:
    """(N,11) float32: normalised position, unit quaternion (w >= 0), log-scale - log(scale),
    exist."""
    c = cloud.numpy()
    out = np.empty((len(c), GEOMETRY_DIM), np.float32)
    out[:, GEO_POSITION] = (c.means.astype(np.float64) - np.asarray(center, np.float64)) / scale
    out[:, GEO_QUAT] = quaternions.canonical(c.quats.astype(np.float64))
    out[:, GEO_LOG_SCALE] = np.clip(c.scales, *LOG_SCALE_RANGE) - np.log(scale)
    out[:, GEO_EXIST] = exist
    return out


def appearance_features(cloud: GaussianCloud, exist: float = 1.0) -> np.ndarray:
    """(N,50) float32: SH rest zero-padded to degree 3 and flattened coefficient-major (index
    k*3 + channel), raw SH DC (3), opacity logit (1), exist."""
    c = cloud.numpy().with_sh_degree(3)
    out = np.empty((len(c), APPEARANCE_DIM), np.float32)
    out[:, APP_SH_REST] = c.sh_rest.reshape(len(c), 45)
    out[:, APP_SH_DC] = c.sh_dc
    out[:, APP_OPACITY] = c.opacities
    out[:, APP_EXIST] = exist
    return out


def cloud_from_features(geometry, appearance, center, scale: float, sh_degree: int = 3, *, means=None,
                        bounded: bool = False) -> GaussianCloud:
    """Inverse of `geometry_features` / `appearance_features` (exist columns ignored). `means`:
    world positions (float64) to use instead of the features' own (which are rounded in the
    normalised frame). `bounded`: a cloud that renders and writes whatever the features hold
    (predicted ones): non-finite values become 0, log-scales and opacity logits are clipped to
    the ranges `GaussianCloud.validate` accepts, SH coefficients to +-1e3, quaternions made unit."""
    g = np.asarray(geometry, np.float64).reshape(-1, GEOMETRY_DIM)
    a = np.asarray(appearance, np.float32).reshape(-1, APPEARANCE_DIM)
    if len(g) != len(a):
        raise ValueError(f"cloud_from_features: {len(g)} geometry rows but {len(a)} appearance rows")
    k = SH_REST_COUNTS[sh_degree]
    pos = g[:, GEO_POSITION] * scale + np.asarray(center, np.float64) if means is None else np.asarray(means)
    if bounded:
        big = np.finfo(np.float32).max / 4
        g, a, pos = _finite(g), np.clip(_finite(a), -BOUNDED_SH, BOUNDED_SH), np.clip(_finite(pos), -big, big)
    log_scales = g[:, GEO_LOG_SCALE] + math.log(scale)
    quats = g[:, GEO_QUAT].astype(np.float32)
    opacities = a[:, APP_OPACITY]
    if bounded:
        log_scales = np.clip(log_scales, *EXTREME_LOG_SCALE)
        quats = quaternions.normalize(quats)
        opacities = np.clip(opacities, *OPACITY_LOGIT_RANGE)
    return GaussianCloud(
        means=pos.astype(np.float32),
        scales=log_scales.astype(np.float32),
        quats=quats,
        opacities=opacities.copy(),
        sh_dc=a[:, APP_SH_DC].copy(),
        sh_rest=a[:, APP_SH_REST].reshape(-1, 15, 3)[:, :k].copy(),
    )


def _finite(x: np.ndarray) -> np.ndarray:
    return x if np.isfinite(x).all() else np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)


# ------------------------------------------------------------------ batches

@dataclass
class LineageBatch:
    """Lineages of M Gaussians over T stages: geometry (M,T,11), appearance (M,T,50) float32,
    ids (M,) int64 of the Gaussians whose lineages these are (alive at the last node)."""

    geometry: np.ndarray
    appearance: np.ndarray
    ids: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass
class Transition:
    """Stage s-1 -> s, what the VAEs learn from: the lineages (T = s nodes) of the M Gaussians
    alive at s-1, history_geometry (M,T,11) and history_appearance (M,T,50), and their children
    at s (itself first if it survived, then new Gaussians whose parent it is, by id), padded to C
    slots: child_geometry (M,C,11), child_appearance (M,C,50), child_mask (M,C). `densified`
    (M,): the Gaussian spawned one that is not itself (default: two or more children). From a
    training run, also the ids (`history_ids` (M,), `child_ids` (M,C), -1 in empty slots), how
    many children did not fit in C slots (`dropped`) and how many stage-s Gaussians have no parent
    at s-1 (`orphans`)."""

    history_geometry: np.ndarray
    history_appearance: np.ndarray
    child_geometry: np.ndarray
    child_appearance: np.ndarray
    child_mask: np.ndarray
    stage: int = 1
    source: str = ""
    densified: np.ndarray | None = None
    history_ids: np.ndarray | None = None
    child_ids: np.ndarray | None = None
    dropped: int = 0
    orphans: int = 0

    def __post_init__(self):
        m, t = self.history_geometry.shape[:2]
        geo, app = GEOMETRY_DIM, APPEARANCE_DIM
        shapes = {"history_geometry": (m, t, geo), "history_appearance": (m, t, app),
                  "child_geometry": (m, None, geo), "child_appearance": (m, None, app), "child_mask": (m, None)}
        for name, shape in shapes.items():
            got = getattr(self, name).shape
            if len(got) != len(shape) or any(s is not None and s != g for s, g in zip(shape, got)):
                raise ValueError(f"Transition.{name} has shape {got}, expected {shape} (None = any)")
        if self.densified is None:
            self.densified = self.child_mask.sum(1) >= 2
        self.densified = np.asarray(self.densified, bool).reshape(m)

    def __len__(self) -> int:
        return len(self.history_geometry)

    def subset(self, index) -> Transition:
        """The lineages `index` (ids kept; `dropped` and `orphans` are of the whole step)."""
        rows = ("history_geometry", "history_appearance", "child_geometry", "child_appearance", "child_mask",
                "densified", "history_ids", "child_ids")
        return dataclasses.replace(self, **{f: getattr(self, f)[index] for f in rows if getattr(self, f) is not None})


@dataclass
class Snapshot:
    """Every Gaussian alive at one stage boundary: raw parameters (numpy), ids, parents."""

    cloud: GaussianCloud
    ids: np.ndarray
    parents: np.ndarray

    def __len__(self) -> int:
        return len(self.cloud)


# ------------------------------------------------------------------ lineage

class Lineage:
    """Snapshots of a progressive run plus its training resolutions and scene normalisation
    (positions become (x - center) / scale, log-scales lose log(scale))."""

    def __init__(self, center=None, scale: float | None = None):
        self.snapshots: list[Snapshot] = []
        self.resolutions: list[int] = []
        self.center = np.zeros(3) if center is None else np.asarray(center, np.float64).reshape(3)
        self.scale = 1.0 if scale is None else float(scale)
        self._index_cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._feature_cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    # ------------------------------------------------------------ building
    @property
    def n_stages(self) -> int:
        return len(self.snapshots)

    def __len__(self) -> int:
        return self.n_stages

    def set_normalization(self, center, scale: float) -> None:
        if not (np.all(np.isfinite(center)) and np.isfinite(scale) and scale > 0):
            raise ValueError(f"Lineage normalisation needs a finite centre and a positive scale, got "
                             f"{center}, {scale}")
        self.center = np.asarray(center, np.float64).reshape(3)
        self.scale = float(scale)
        self._feature_cache.clear()

    def add_stage(self, cloud: GaussianCloud, ids, parents, resolution: int) -> None:
        """Append the snapshot of the next stage, checking the lineage invariants: ids unique and
        never reused after being pruned; at stage 0 every parent is -1; later a parent is -1 or
        an id alive at the previous stage, and a Gaussian alive there is its own parent."""
        cloud = cloud.numpy()
        ids = np.asarray(ids).astype(np.int64, copy=True).reshape(-1)
        parents = np.asarray(parents).astype(np.int64, copy=True).reshape(-1)
        s = self.n_stages
        if len(ids) != len(cloud) or len(parents) != len(cloud):
            raise ValueError(f"stage {s}: {len(cloud)} Gaussians but {len(ids)} ids and "
                             f"{len(parents)} parents")
        if len(np.unique(ids)) != len(ids):
            raise ValueError(f"stage {s}: Gaussian ids are not unique")
        if (ids < 0).any():
            raise ValueError(f"stage {s}: Gaussian ids must be >= 0")
        if s == 0:
            if (parents != -1).any():
                raise ValueError("stage 0: every parent must be -1")
        else:
            prev = self.snapshots[-1].ids
            has_parent = parents >= 0
            bad = has_parent & ~np.isin(parents, prev)
            if bad.any():
                raise ValueError(f"stage {s}: {int(bad.sum())} parent id(s) not alive at stage {s - 1}, "
                                 f"e.g. {int(parents[bad][0])}")
            survived = np.isin(ids, prev)
            if (parents[survived] != ids[survived]).any():
                raise ValueError(f"stage {s}: a Gaussian alive at stage {s - 1} must be its own parent")
            earlier = np.concatenate([snap.ids for snap in self.snapshots])
            reused = ~survived & np.isin(ids, earlier)
            if reused.any():
                raise ValueError(f"stage {s}: id {int(ids[reused][0])} was pruned earlier and reappears")
        self.snapshots.append(Snapshot(cloud, ids, parents))
        self.resolutions.append(int(resolution))

    @classmethod
    def from_cloud(cls, cloud: GaussianCloud, center=None, scale: float | None = None,
                   resolution: int = 0) -> Lineage:
        """One-node lineages for a cloud without history. Ids come from the cloud's `gvae_id`
        property when it has unique ones, else 0..N-1; the normalisation from the cloud itself
        (`GaussianCloud.normalization`) unless given."""
        cloud = cloud.numpy()
        ids = cloud.extra.get("gvae_id")
        if ids is None or ids.ndim != 1 or len(np.unique(ids)) != len(ids) or (np.asarray(ids) < 0).any():
            ids = np.arange(len(cloud), dtype=np.int64)
        if center is None or scale is None:
            c, s = cloud.normalization()
            center = c if center is None else center
            scale = s if scale is None else scale
        lin = cls(center, scale)
        lin.add_stage(cloud.replace(extra={}), ids, np.full(len(cloud), -1, np.int64), resolution)
        return lin

    def prefix(self, n_stages: int) -> Lineage:
        """The first `n_stages` stages, normalised from the last of them (as the trainer does
        after each stage): what a run stopped there would have recorded, with nothing from later
        stages (the lineage to refine when later stages are kept for evaluation)."""
        if not 1 <= n_stages <= self.n_stages:
            raise ValueError(f"prefix: n_stages must be in 1..{self.n_stages}, got {n_stages}")
        out = Lineage()
        for s in range(n_stages):
            snap = self.snapshots[s]
            out.add_stage(snap.cloud, snap.ids, snap.parents, self.resolutions[s])
        out.set_normalization(*self.snapshots[n_stages - 1].cloud.normalization())
        return out

    # ------------------------------------------------------------ access
    def stage_of(self, cloud: GaussianCloud) -> int:
        """The stage whose snapshot `cloud` is (a `stage_<s>.ply` of the run, say): among the
        stages at which every one of the cloud's `gvae_id`s is alive (Gaussians keep their id from
        stage to stage, so there can be several), the one whose positions for those ids are the
        cloud's (the closest; ties: the latest). Without ids, the stages with as many Gaussians as
        the cloud, compared row by row. Raises ValueError when no stage fits."""
        c = cloud.numpy()
        ids = c.extra.get("gvae_id")
        means = np.asarray(c.means, np.float64)
        candidates = []
        for s in range(self.n_stages):
            snap = self.snapshots[s]
            if ids is not None and len(ids) == len(c):
                rows = self.rows_of(s, ids)
                if (rows < 0).any():
                    continue
            elif len(snap) == len(c):
                rows = np.arange(len(c))
            else:
                continue
            gap = float(np.abs(np.asarray(snap.cloud.means, np.float64)[rows] - means).max(initial=0.0))
            candidates.append((gap, -s))
        if not candidates:
            if ids is not None and len(ids) == len(c):
                alive = [int((self.rows_of(s, ids) >= 0).sum()) for s in range(self.n_stages)]
                raise ValueError(f"the cloud's {len(c)} Gaussian ids are not alive together at any stage of the "
                                 f"lineage (alive per stage: {alive})")
            raise ValueError(f"the cloud has {len(c)} Gaussians and no gvae_id property, and no stage of the lineage "
                             f"has that many ({[len(s) for s in self.snapshots]})")
        return -min(candidates)[1]

    def snapshot(self, stage: int) -> Snapshot:
        self._check_stage(stage)
        return self.snapshots[stage]

    def stage_cloud(self, stage: int) -> GaussianCloud:
        """The snapshot as a cloud with int64 extra properties `gvae_id` and `gvae_parent`."""
        snap = self.snapshot(stage)
        return snap.cloud.replace(extra={**snap.cloud.extra, "gvae_id": snap.ids, "gvae_parent": snap.parents})

    def _check_stage(self, stage: int, first: int = 0) -> None:
        if not first <= stage < self.n_stages:
            raise ValueError(f"stage {stage} out of range {first}..{self.n_stages - 1}")

    def rows_of(self, stage: int, ids) -> np.ndarray:
        """Row of each id in the stage's snapshot, -1 where it is not alive there."""
        if stage not in self._index_cache:
            order = np.argsort(self.snapshots[stage].ids, kind="stable")
            self._index_cache[stage] = (self.snapshots[stage].ids[order], order)
        sorted_ids, order = self._index_cache[stage]
        ids = np.asarray(ids, np.int64)
        if len(sorted_ids) == 0:
            return np.full(len(ids), -1, np.int64)
        pos = np.clip(np.searchsorted(sorted_ids, ids), 0, len(sorted_ids) - 1)
        return np.where(sorted_ids[pos] == ids, order[pos], -1)

    def _features(self, stage: int) -> tuple[np.ndarray, np.ndarray]:
        if stage not in self._feature_cache:
            cloud = self.snapshots[stage].cloud
            self._feature_cache[stage] = (geometry_features(cloud, self.center, self.scale),
                                          appearance_features(cloud))
        return self._feature_cache[stage]

    # ------------------------------------------------------------ lineages
    def sequences(self, stage: int) -> LineageBatch:
        """Lineages (T = stage+1 nodes) of every Gaussian alive at `stage`, in snapshot order.
        A node before the Gaussian existed holds its nearest ancestor's snapshot (exist=0); where
        no ancestor is known, the earliest known state of the chain is repeated (exist=0)."""
        self._check_stage(stage)
        ids = self.snapshots[stage].ids
        m, t = len(ids), stage + 1
        src_stage = np.empty((m, t), np.int64)
        src_row = np.empty((m, t), np.int64)
        src_stage[:, stage], src_row[:, stage] = stage, np.arange(m)
        for s in range(stage, 0, -1):
            direct = src_stage[:, s] == s  # chain still inside snapshots (not repeating)
            parent_ids = np.full(m, -1, np.int64)
            parent_ids[direct] = self.snapshots[s].parents[src_row[direct, s]]
            rows = self.rows_of(s - 1, parent_ids)
            ok = direct & (rows >= 0)
            src_stage[:, s - 1] = np.where(ok, s - 1, src_stage[:, s])
            src_row[:, s - 1] = np.where(ok, rows, src_row[:, s])
        geometry = np.empty((m, t, GEOMETRY_DIM), np.float32)
        appearance = np.empty((m, t, APPEARANCE_DIM), np.float32)
        for s in range(t):
            geo, app = self._features(s)
            sel = src_stage == s
            geometry[sel] = geo[src_row[sel]]
            appearance[sel] = app[src_row[sel]]
        # exist: the node is this Gaussian's own snapshot (ids persist, so compare ids).
        exist = np.zeros((m, t), np.float32)
        for s in range(t):
            sel = src_stage[:, s] == s
            exist[sel, s] = (self.snapshots[s].ids[src_row[sel, s]] == ids[sel]).astype(np.float32)
        geometry[..., GEO_EXIST] = exist
        appearance[..., APP_EXIST] = exist
        return LineageBatch(geometry, appearance, ids.copy())

    def transitions(self, stage: int, max_children: int = 8, source: str = "") -> Transition:
        """The step stage-1 -> stage: lineages of the Gaussians alive at stage-1 and their
        children at `stage`, at most `max_children` per parent (the rest are counted in
        `dropped`)."""
        self._check_stage(stage, first=1)
        if max_children < 1:
            raise ValueError(f"max_children must be >= 1, got {max_children}")
        history = self.sequences(stage - 1)
        m = len(history)
        snap = self.snapshots[stage]
        group = self.rows_of(stage - 1, snap.parents)
        has = group >= 0
        orphans = int((~has).sum())
        rows = np.flatnonzero(has)
        g = group[rows]
        not_self = (snap.ids[rows] != snap.parents[rows]).astype(np.int64)
        order = np.lexsort((snap.ids[rows], not_self, g))
        rows, g = rows[order], g[order]
        counts = np.bincount(g, minlength=m)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        rank = np.arange(len(rows)) - starts[g]
        c = int(min(max(int(counts.max()) if m else 0, 1), max_children))
        keep = rank < c
        dropped = int((~keep).sum())
        rows, g, rank = rows[keep], g[keep], rank[keep]
        geo, app = self._features(stage)
        child_geometry = np.zeros((m, c, GEOMETRY_DIM), np.float32)
        child_appearance = np.zeros((m, c, APPEARANCE_DIM), np.float32)
        child_mask = np.zeros((m, c), bool)
        child_ids = np.full((m, c), -1, np.int64)
        child_geometry[g, rank] = geo[rows]
        child_appearance[g, rank] = app[rows]
        child_mask[g, rank] = True
        child_ids[g, rank] = snap.ids[rows]
        not_self = (child_ids != history.ids[:, None]) & child_mask
        return Transition(history.geometry, history.appearance, child_geometry, child_appearance, child_mask,
                          stage=stage, source=source, densified=not_self.any(1), history_ids=history.ids,
                          child_ids=child_ids, dropped=dropped, orphans=orphans)

    # ------------------------------------------------------------ files
    def save(self, path) -> Path:
        """Write one `.npz` (numpy arrays only), atomically: a failed write leaves no file."""
        path = Path(path)
        arrays = {"format": np.array(_FORMAT), "resolutions": np.asarray(self.resolutions, np.int64),
                  "center": self.center.astype(np.float64), "scale": np.float64(self.scale)}
        for s, snap in enumerate(self.snapshots):
            for name in _PARAMS:
                arrays[f"s{s}_{name}"] = np.asarray(getattr(snap.cloud, name), np.float32)
            arrays[f"s{s}_ids"] = snap.ids
            arrays[f"s{s}_parents"] = snap.parents
        return atomic_write(path, lambda f: np.savez(f, **arrays))

    @classmethod
    def load(cls, path) -> Lineage:
        """Read a file written by `save`; bad or foreign files raise ValueError naming the file."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such lineage file")
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except Exception as exc:  # zip / format errors from numpy
            raise ValueError(f"{path}: not a lineage file ({exc})") from exc
        if "format" not in arrays or str(arrays["format"]) != _FORMAT:
            raise ValueError(f"{path}: not a lineage file (format tag missing or not {_FORMAT!r})")
        try:
            lin = cls(arrays["center"], float(arrays["scale"]))
            for s, res in enumerate(arrays["resolutions"]):
                cloud = GaussianCloud(**{n: arrays[f"s{s}_{n}"] for n in _PARAMS})
                lin.add_stage(cloud, arrays[f"s{s}_ids"], arrays[f"s{s}_parents"], int(res))
        except KeyError as exc:
            raise ValueError(f"{path}: lineage file is missing array {exc}") from exc
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from exc
        return lin
