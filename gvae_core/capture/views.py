"""Views to score a cloud from: a few of the capture's cameras, or cameras placed around it.

`scoring_views` picks a few of a capture's cameras (`gvae_core.capture.read_capture`), spread
out; `placed_views` / `default_views` place cameras when there are none: outside an object, all
around it, below too (a closed shell is an object), or inside a scene that surrounds its centre,
only when the evidence is strong (`surround`: its far shell is coarser than what it surrounds, as
training from inside makes it), with extra views that look at what the scoring ones cannot
(`PlacedViews.extra`, for what is dropped as unseen). The Hessian (`gvae_core.hessian`) and
compaction are computed from these. numpy only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..antialias import DILATION_KEY, FILTER_KEY
from ..camera import Camera
from ..cloud import GaussianCloud
from ..conventions import LOG_SCALE_RANGE

__all__ = ["scoring_views", "in_view", "fibonacci_lattice", "default_views", "placed_views", "PlacedViews",
           "outside_views", "inside_views", "surround", "surround_radius", "Surround", "DEFAULT_VIEWS",
           "DEFAULT_RESOLUTION"]

#: Views the Hessian is computed from by default, and their height in pixels (`scoring_views`,
#: `default_views`).
DEFAULT_VIEWS = 4
DEFAULT_RESOLUTION = 256


# ------------------------------------------------------------------------ scoring views


#: Direction cells (a Fibonacci lattice around the centre) that `surround` counts.
SURROUND_CELLS = 64
#: A scene surrounds its centre (`surround`) when the farthest quarter of its Gaussians from the
#: centre is at least this much coarser than the nearest half: in the median size of a training
#: pixel where the cloud stores it (`_pixel_sizes`), else of the Gaussians along their surface
#: (texture makes those vary more: the project's objects measure 0.84-1.11 and 0.87-1.31). A cloud
#: trained from cameras inside it samples its far shell more coarsely than what stands near the
#: cameras, while one trained from outside (a closed object: a head, a box) samples its surface at
#: least as finely as anything inside it. A closed shell without that evidence is an object. ...
SURROUND_COARSER = 1.5
SURROUND_COARSER_SIZES = 2.0
#: ... and its shell (the Gaussians coarser than midway, in log size, between the two) lies in at
#: least this share of the directions (SURROUND_CELLS cells) around what it surrounds (the finer
#: ones, from their median point: an object whose coarse parts are on one side, a plate with its
#: fine detail underneath, measures 0.55-0.58, a room 0.78-1.0) ...
SURROUND_ENCLOSED = 0.7
#: ... and what it surrounds is at least this share of the cloud.
SURROUND_CONTENT = 0.1
#: Field of view of views placed inside a scene, and of views placed around an object.
INSIDE_FOV = math.radians(70.0)
OUTSIDE_FOV = math.radians(50.0)


@dataclass(frozen=True)
class Surround:
    """A scene that surrounds its centre (`surround`): the radius within which what it surrounds
    lies (`inner`: 95% of it) and where the shell begins (`outer`: beyond 5% of it), the evidence
    (`enclosed`: share of the directions around what it surrounds its shell lies in; `coarser`:
    how much coarser it is than the nearest half; `content`: share of the Gaussians the shell
    surrounds), and where cameras can stand (`positions` (K, 3), world frame, one per direction
    with free space: nearest the distance that frames what the shell surrounds)."""

    inner: float
    outer: float
    enclosed: float
    coarser: float
    content: float
    positions: np.ndarray


def fibonacci_lattice(cells: int) -> np.ndarray:
    """(cells, 3) unit vectors, a Fibonacci lattice: about evenly spread over the sphere."""
    k = np.arange(cells) + 0.5
    z = 1.0 - 2.0 * k / cells
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    return np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)


def _pixel_sizes(cloud: GaussianCloud) -> tuple[np.ndarray, float]:
    """Per Gaussian, how coarsely its training sampled it, and the SURROUND_COARSER* threshold
    that goes with it: the stored size of a training pixel (`filter_3D` or `gvae_dilation_3D`,
    world units) where the cloud has one, else the Gaussian's size along its surface (the geometric
    mean of its two largest scales)."""
    for key in (FILTER_KEY, DILATION_KEY):
        if key in cloud.extra and np.ndim(cloud.extra[key]) == 1:
            return np.asarray(cloud.extra[key], np.float64), SURROUND_COARSER
    log_scales = np.sort(np.clip(np.asarray(cloud.scales, np.float64), *LOG_SCALE_RANGE), axis=1)
    return np.exp(0.5 * (log_scales[:, 1] + log_scales[:, 2])), SURROUND_COARSER_SIZES


def _around(src: GaussianCloud, center: np.ndarray, sample: int):
    """(rows, centres, centres - `center`, their distances): of at most `sample` finite Gaussians of
    `src` (a fixed random subsample decides as well as all of them)."""
    p = np.asarray(src.means, np.float64)
    ok = np.flatnonzero(np.isfinite(p).all(1))
    if len(ok) > sample:
        ok = np.sort(np.random.default_rng(0).choice(ok, sample, replace=False))
    rel = p[ok] - center
    return ok, p[ok], rel, np.linalg.norm(rel, axis=1)


def surround(cloud: GaussianCloud, normalization=None, *, sample: int = 200_000) -> Surround | None:
    """Whether `cloud` is a scene around its robust centre, seen from inside (a capture with its
    background, a room), and where cameras can stand in it; None for an object. A scene when the
    farthest quarter of the Gaussians from the centre is SURROUND_COARSER coarser than the nearest
    half (`_pixel_sizes`), the finer ones (what the coarser shell surrounds) are SURROUND_CONTENT
    of them, and the coarser ones lie in SURROUND_ENCLOSED of the directions around them. A
    closed shell without that evidence (a head with a few floaters inside, a box) is an object. At
    most `sample` Gaussians are looked at (a subsample decides as well)."""
    src = cloud.numpy()
    center, _ = normalization or src.normalization()
    ok, p, rel, r = _around(src, center, sample)
    if len(ok) < 64:
        return None
    near_half, far_quarter = r <= np.median(r), r >= np.percentile(r, 75.0)
    size, threshold = _pixel_sizes(src)
    size = np.maximum(size[ok], 1e-30)
    fine, coarse = float(np.median(size[near_half])), float(np.median(size[far_quarter]))
    coarser = coarse / fine
    if not coarser >= threshold:
        return None
    content = size < math.sqrt(fine * coarse)
    if content.mean() < SURROUND_CONTENT:
        return None
    lattice = fibonacci_lattice(SURROUND_CELLS)
    around = p[~content] - np.median(p[content], axis=0)
    enclosed = len(np.unique(np.argmax(around @ lattice.T, axis=1))) / SURROUND_CELLS
    if enclosed < SURROUND_ENCLOSED:
        return None
    inner, outer = float(np.percentile(r[content], 95.0)), float(np.percentile(r[~content], 5.0))
    shell_cell = np.argmax(rel[~content] @ lattice.T, axis=1)
    reach = np.zeros(SURROUND_CELLS)  # per direction, where its shell begins
    for k in np.unique(shell_cell):
        reach[k] = np.percentile(r[~content][shell_cell == k], 5.0)
    positions = _free_positions(src.select(ok), center, lattice, reach, inner)
    if len(positions) == 0:
        return None
    return Surround(inner, outer, enclosed, coarser, float(content.mean()), positions)


def _free_positions(cloud: GaussianCloud, center: np.ndarray, lattice: np.ndarray, reach: np.ndarray,
                    inner: float) -> np.ndarray:
    """Where cameras can stand inside a scene, one per direction from the centre that has room:
    the point along direction k, short of where its shell begins (`reach[k]`), nearest the distance
    from which what the shell surrounds fills a view of INSIDE_FOV (1.2 times its radius `inner`
    across), that is free (its nearest Gaussian farther than its own largest standard deviation,
    than 1% of the scene's size and than a tenth of the way to the centre) and sees the centre over
    free space for the first half of the way; the freest first."""
    from scipy.spatial import cKDTree  # noqa: PLC0415 - scipy is slow to import

    p = np.asarray(cloud.means, np.float64)
    size = np.exp(np.clip(np.asarray(cloud.scales, np.float64), *LOG_SCALE_RANGE).max(1))
    tree = cKDTree(p)
    margin = 0.01 * float(np.linalg.norm(np.ptp(p, axis=0)))

    def free(points: np.ndarray, room) -> tuple[np.ndarray, np.ndarray]:
        dist, nearest = tree.query(points)
        return (dist > size[nearest]) & (dist > room), dist

    frame = 1.2 * inner / math.sin(0.5 * INSIDE_FOV)
    way = np.linspace(0.0, 0.5, 8)  # the first half of the way to the centre
    found, clearance = [], []
    for d, limit in zip(lattice, reach):
        if limit <= 0:
            continue
        radii = np.geomspace(0.05, 0.9, 32) * limit
        radii = radii[np.argsort(np.abs(np.log(radii / frame)), kind="stable")]  # nearest the framing distance first
        ok, dist = free(center + radii[:, None] * d, np.maximum(0.1 * radii, margin))
        for i in np.flatnonzero(ok):
            sight = center + (radii[i] * (1.0 - way))[:, None] * d
            if free(sight, 0.0)[0].all():
                found.append(center + radii[i] * d)
                clearance.append(dist[i])
                break
    if not found:
        return np.zeros((0, 3))
    return np.asarray(found)[np.argsort(clearance, kind="stable")[::-1]]


def surround_radius(cloud: GaussianCloud, normalization=None) -> tuple[float, float] | None:
    """(`Surround.inner`, `Surround.outer`) of a scene that surrounds its centre, else None."""
    found = surround(cloud, normalization)
    return None if found is None else (found.inner, found.outer)


def _spread(directions: np.ndarray, count: int) -> list[int]:
    """`count` indices of `directions` spread out by farthest-point sampling (from the first)."""
    pick = [0]
    dist = np.linalg.norm(directions - directions[0], axis=1)
    while len(pick) < min(count, len(directions)):
        nxt = int(np.argmax(dist))
        pick.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(directions - directions[nxt], axis=1))
    return pick


def outside_views(cloud: GaussianCloud, views: int = DEFAULT_VIEWS, resolution: int = DEFAULT_RESOLUTION,
                  fov_x: float = OUTSIDE_FOV, normalization=None) -> list[Camera]:
    """`views` cameras all around the cloud's robust centre, below it as well as above (a
    Fibonacci lattice over the whole sphere, z up), each from where a sphere of 1.4 half-extents
    just fits its view, all looking at the centre."""
    center, half = normalization or cloud.normalization()
    radius = 1.4 * half / math.sin(0.5 * fov_x)
    return [Camera.look_at(center + radius * d, center, (0.0, 0.0, 1.0), width=resolution, height=resolution,
                           fov_x=fov_x) for d in fibonacci_lattice(max(int(views), 1))]


@dataclass
class PlacedViews:
    """Views placed to look at a cloud without its capture's cameras (`placed_views`): `scoring`,
    the views to score and compare pictures from; `extra`, views that look at what those cannot
    (only which Gaussians they see counts: none for an object); `surround`: the evidence that the
    cloud is a scene seen from inside, or None for an object."""

    scoring: list[Camera]
    extra: list[Camera]
    surround: Surround | None


def placed_views(cloud: GaussianCloud, views: int = DEFAULT_VIEWS, resolution: int = DEFAULT_RESOLUTION,
                 fov_x: float = OUTSIDE_FOV, normalization=None) -> PlacedViews:
    """Views that see what is there, without the capture's cameras. An object (every cloud without
    strong evidence of the opposite, `surround`; a closed shell is an object) is scored from
    `views` views outside it, all around, below too (`outside_views`); they need no extra views.
    A scene that surrounds its centre is scored from `views` views inside it, in its free space
    (`Surround.positions`, spread out over the directions around the centre), looking at its
    centre with a field of view of INSIDE_FOV; its extra views are the six faces of a cube around
    its freest point (every direction from inside) and `views` views all around it from outside
    (what only they see, the far side of its walls, is then not taken for unseen either)."""
    normalization = normalization or cloud.normalization()
    found = surround(cloud, normalization)
    if found is None:
        return PlacedViews(outside_views(cloud, views, resolution, fov_x, normalization), [], None)
    inside = _looking_at(found.positions, normalization[0], views, resolution)
    eye = found.positions[0]
    cube = [Camera.look_at(eye, eye + d, (0.0, 0.0, 1.0), width=resolution, height=resolution,
                           fov_x=math.radians(90.0)) for d in np.concatenate([np.eye(3), -np.eye(3)])]
    return PlacedViews(inside, cube + outside_views(cloud, views, resolution, normalization=normalization), found)


def inside_views(cloud: GaussianCloud, views: int = DEFAULT_VIEWS, resolution: int = DEFAULT_RESOLUTION,
                 normalization=None, *, sample: int = 200_000) -> list[Camera]:
    """Up to `views` cameras in the free space inside a cloud, whatever it was taken for, looking at
    its robust centre with a field of view of INSIDE_FOV, each along another direction from it
    (`_free_positions`, short of the far side of the cloud in that direction, framing its nearer
    half): what views from outside cannot see of a scene taken for an object (a room whose far
    walls its training sampled hardly more coarsely than its furniture). None where there is no
    free space."""
    src = cloud.numpy()
    center, _ = normalization or src.normalization()
    ok, _, rel, r = _around(src, center, sample)
    if len(ok) < 64:
        return []
    lattice = fibonacci_lattice(SURROUND_CELLS)
    cell = np.argmax(rel @ lattice.T, axis=1)
    reach = np.zeros(SURROUND_CELLS)  # per direction, the far side of the cloud
    for k in np.unique(cell):
        reach[k] = np.percentile(r[cell == k], 95.0)
    positions = _free_positions(src.select(ok), center, lattice, reach, float(np.median(r)))
    if len(positions) == 0:
        return []
    return _looking_at(positions, center, views, resolution)


def _looking_at(positions: np.ndarray, center: np.ndarray, views: int, resolution: int) -> list[Camera]:
    """`views` cameras at `positions` (the first, then spread out over their directions from
    `center`), looking at `center` with a field of view of INSIDE_FOV."""
    rel = positions - center
    directions = rel / np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1e-30)
    return [Camera.look_at(positions[i], center, (0.0, 0.0, 1.0), width=resolution, height=resolution,
                           fov_x=INSIDE_FOV) for i in _spread(directions, max(int(views), 1))]


def default_views(cloud: GaussianCloud, views: int = DEFAULT_VIEWS, resolution: int = DEFAULT_RESOLUTION,
                  fov_x: float = OUTSIDE_FOV, normalization=None) -> list[Camera]:
    """The views to score a cloud from without its capture's cameras: `placed_views(...).scoring`
    (outside an object, all around; inside a scene that surrounds its centre). `normalization`:
    the cloud's (centre, scale) when known (`GaussianCloud.normalization`)."""
    return placed_views(cloud, views, resolution, fov_x, normalization).scoring


def in_view(cameras: Sequence[Camera], cloud: GaussianCloud, sample: int = 20_000) -> np.ndarray:
    """(len(cameras), K) bool: which of K of the cloud's finite centres (all, or a fixed random
    `sample` of them) each camera has in its image, in front of it."""
    p = np.asarray(cloud.numpy().means, np.float64)
    p = p[np.isfinite(p).all(1)]
    if len(p) > sample:
        p = p[np.random.default_rng(0).choice(len(p), sample, replace=False)]
    out = np.zeros((len(cameras), len(p)), bool)
    for i, cam in enumerate(cameras):
        uv, z = cam.project(p)
        with np.errstate(invalid="ignore"):
            out[i] = (z > 0.01) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height)
    return out


def scoring_views(cameras: Sequence[Camera], views: int = DEFAULT_VIEWS, resolution: int = DEFAULT_RESOLUTION,
                  cloud: GaussianCloud | None = None) -> list[Camera]:
    """`views` of the capture's `cameras` to compute the Hessian from: those that see the cloud
    (when given: at least 1% of its centres in the image, in front of the camera), spread out by
    farthest-point sampling on camera centre and viewing direction (from the camera that sees the
    most), each scaled to `resolution` pixels high when it is larger (a capture's full-size images
    cost time and add little to the score). All of them when `views` is 0 or covers them all.
    Raises ValueError when no camera sees the cloud (cameras of another frame, say)."""
    cams = list(cameras)
    if not cams:
        raise ValueError("scoring views: no cameras")
    seen = np.ones(len(cams))
    if cloud is not None and len(cloud):
        sees = in_view(cams, cloud)
        seen = sees.mean(1) if sees.shape[1] else np.zeros(len(cams))
        keep = np.flatnonzero(seen >= 0.01)
        if len(keep) == 0:
            raise ValueError(f"none of the {len(cams)} cameras sees the cloud (are they in the cloud's frame? a "
                             f"COLMAP model or transforms.json of the capture the cloud was trained from)")
        cams, seen = [cams[i] for i in keep], seen[keep]
    if 0 < views < len(cams):
        centres = np.stack([c.center for c in cams])
        dirs = np.stack([c.rotation[2] for c in cams])
        extent = max(float(np.ptp(centres, axis=0).max()), 1e-12)
        feats = np.concatenate([centres / extent, 0.5 * dirs], 1)
        first = int(np.argmax(seen))
        pick = [first]
        dist = np.linalg.norm(feats - feats[first], axis=1)
        while len(pick) < views:
            nxt = int(np.argmax(dist))
            pick.append(nxt)
            dist = np.minimum(dist, np.linalg.norm(feats - feats[nxt], axis=1))
        cams = [cams[i] for i in sorted(pick)]
    return [c.scaled(resolution) if c.height > resolution else c for c in cams]
