"""Evaluation metrics: exact point-to-mesh distances, Chamfer, image scores."""

import math

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from gvae_core import Camera, GaussianCloud
from gvae_core.antialias import with_filter_3d
from gvae_core.datasets import Views
from gvae_core.metrics.geometry import (MeshDistance, chamfer, closest_point_on_triangles,
                                        point_mesh_distance_reference, read_mesh_ply)
from gvae_core.metrics.image import image_scores, render_views
from gvae_core.scenes.build import write_mesh_ply


def _segment_closest(p, a, b):
    ab = b - a
    t = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-300), 0.0, 1.0)
    return a + t * ab


def _closest_by_projection(p, a, b, c):
    """Independent derivation: the plane projection if it falls inside, else the best edge point."""
    n = np.cross(b - a, c - a)
    nn = np.dot(n, n)
    candidates = [_segment_closest(p, a, b), _segment_closest(p, b, c), _segment_closest(p, c, a)]
    if nn > 1e-24:
        q = p - np.dot(p - a, n) / nn * n
        # barycentric coordinates of q
        v0, v1, v2 = b - a, c - a, q - a
        d00, d01, d11 = np.dot(v0, v0), np.dot(v0, v1), np.dot(v1, v1)
        d20, d21 = np.dot(v2, v0), np.dot(v2, v1)
        den = d00 * d11 - d01 * d01
        v = (d11 * d20 - d01 * d21) / den
        w = (d00 * d21 - d01 * d20) / den
        if v >= 0 and w >= 0 and v + w <= 1:
            candidates.append(q)
    return min(candidates, key=lambda x: np.linalg.norm(p - x))


def _sphere_mesh(n=200, seed=0):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return v, ConvexHull(v).simplices


def test_closest_point_matches_independent_derivation():
    rng = np.random.default_rng(0)
    n = 400
    a, b, c = (rng.normal(size=(n, 3)) for _ in range(3))
    c[:20] = a[:20] + 0.5 * (b[:20] - a[:20])   # collinear (zero-area) triangles
    b[20:30] = a[20:30]                          # two equal corners
    p = rng.normal(size=(n, 3)) * 2
    p[30:60] = (a[30:60] + b[30:60] + c[30:60]) / 3 + 1e-3 * rng.normal(size=(30, 3))  # just off the face
    got = closest_point_on_triangles(p, a, b, c)
    assert np.isfinite(got).all()
    for i in range(n):
        want = _closest_by_projection(p[i], a[i], b[i], c[i])
        assert np.linalg.norm(p[i] - got[i]) == pytest.approx(np.linalg.norm(p[i] - want), abs=1e-9)


def test_mesh_distance_is_exact_on_a_sphere_mesh():
    verts, tris = _sphere_mesh()
    rng = np.random.default_rng(1)
    pts = np.concatenate([rng.normal(size=(300, 3)) * 0.6,             # inside
                          rng.normal(size=(300, 3)) * 3.0,             # far outside
                          verts[:100] * (1 + 1e-4)])                   # on the surface
    fast = MeshDistance(verts, tris)(pts)
    ref = point_mesh_distance_reference(pts, verts, tris)
    np.testing.assert_allclose(fast, ref, atol=1e-12)


def test_chamfer_on_a_plane():
    # a unit square in z = 0, two triangles
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    g = np.stack(np.meshgrid(np.linspace(0.05, 0.95, 10), np.linspace(0.05, 0.95, 10)), -1).reshape(-1, 2)
    surface = np.c_[g, np.zeros(len(g))]
    lifted = surface + [0, 0, 0.02]
    r = chamfer(lifted, surface, (verts, tris))
    assert r.accuracy == pytest.approx(0.02, abs=1e-12)
    assert r.completeness == pytest.approx(0.02, abs=1e-12)
    assert r.chamfer == pytest.approx(0.02, abs=1e-12)
    # extra centres on the surface improve completeness only where they fill gaps
    half = chamfer(lifted[::2], surface, (verts, tris))
    assert half.completeness > r.completeness
    # a far floater raises accuracy by its distance / N
    floater = chamfer(np.r_[lifted, [[0.5, 0.5, 1.0]]], surface, (verts, tris))
    assert floater.accuracy == pytest.approx((0.02 * 100 + 1.0) / 101, abs=1e-12)
    assert floater.weighted_accuracy == pytest.approx(floater.accuracy, abs=1e-12)  # no weights: the same
    # weighted by opacity, a nearly transparent floater hardly counts
    faint = chamfer(np.r_[lifted, [[0.5, 0.5, 1.0]]], surface, (verts, tris), weights=np.r_[np.ones(100), 0.01])
    assert faint.weighted_accuracy == pytest.approx((0.02 * 100 + 0.01) / 100.01, abs=1e-12)
    assert faint.accuracy == floater.accuracy
    # without a mesh, accuracy is measured against the surface points
    assert chamfer(surface, surface).chamfer == 0.0


def test_chamfer_bad_and_empty_inputs():
    surface = np.zeros((5, 3))
    with pytest.raises(ValueError, match="not finite"):
        chamfer(np.array([[0, 0, np.nan]]), surface)
    with pytest.raises(ValueError, match="surface"):
        chamfer(np.zeros((2, 3)), np.zeros((0, 3)))
    assert math.isinf(chamfer(np.zeros((0, 3)), surface).chamfer)
    for bad in (np.ones(3), np.array([1.0, np.nan]), np.array([1.0, -1.0])):
        with pytest.raises(ValueError, match="weights"):
            chamfer(np.zeros((2, 3)), surface, weights=bad)
    with pytest.raises(ValueError, match="no triangles"):
        MeshDistance(np.zeros((3, 3)), np.zeros((0, 3), int))


def test_mesh_ply_round_trip(tmp_path):
    verts, tris = _sphere_mesh(50)
    write_mesh_ply(tmp_path / "mesh.ply", verts, tris)
    v, t = read_mesh_ply(tmp_path / "mesh.ply")
    np.testing.assert_allclose(v, verts, atol=1e-6)
    np.testing.assert_array_equal(t, tris)
    (tmp_path / "bad.ply").write_bytes(b"not a ply")
    with pytest.raises(ValueError, match="bad.ply"):
        read_mesh_ply(tmp_path / "bad.ply")


def test_image_scores_of_a_cloud_against_its_own_renders():
    rng = np.random.default_rng(0)
    n = 200
    cloud = GaussianCloud(means=rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32),
                          scales=np.full((n, 3), math.log(0.05), np.float32),
                          quats=np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
                          opacities=np.full(n, 2.0, np.float32), sh_dc=rng.normal(size=(n, 3)).astype(np.float32))
    cams = [Camera.look_at((0, -3, 1), width=48, height=48, fov_x=0.8), Camera.look_at((2, 2, 1), width=48, height=48,
                                                                                       fov_x=0.8)]
    images = render_views(cloud, Views(cams, np.zeros((2, 48, 48, 3))))
    views = Views(cams, images)  # alpha 1: the renders are the ground truth
    s = image_scores(cloud, views)
    assert s.psnr == 100.0 and s.ssim == pytest.approx(1.0, abs=1e-6) and math.isnan(s.niqe) and s.n_views == 2
    shifted = cloud.replace(means=cloud.means + np.float32(0.05))
    worse = image_scores(shifted, views)
    assert worse.psnr < 40 and worse.ssim < 1.0


def test_image_scores_take_the_antialias_mode():
    rng = np.random.default_rng(1)
    n = 150
    cams = [Camera.look_at((0, -3, 1), width=40, height=40, fov_x=0.8)]
    cloud = GaussianCloud(means=rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32),
                          scales=np.full((n, 3), math.log(0.01), np.float32),
                          quats=np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
                          opacities=np.full(n, 2.0, np.float32), sh_dc=rng.normal(size=(n, 3)).astype(np.float32))
    cloud = with_filter_3d(cloud, cams, resolution=20)
    views = Views(cams, render_views(cloud, Views(cams, np.zeros((1, 40, 40, 3))), antialias="mip"))
    assert image_scores(cloud, views, antialias="mip").psnr == 100.0
    assert image_scores(cloud, views, antialias="classic").psnr < 40.0
