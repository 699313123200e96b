"""A small synthetic problem for the mapper's tests: a ring of exact cameras round a box, exact
correspondences (no images) and the comparison of a reconstruction's state before and after."""
import numpy as np

from geometry_helpers import ring_camera
from stereoseed.geometry.projection import camera_center, project
from stereoseed.features.harris import Features
from stereoseed.matching.containers import Matches

SHAPE = (480, 640)


def box_surface(rng, n, half=0.17, height=0.44):
    """(points (n, 3), outward normals (n, 3)) on the four sides and the top of a box."""
    pts = rng.uniform([-half, -half, 0.0], [half, half, height], size=(n, 3))
    normals = np.zeros((n, 3))
    face = rng.integers(0, 5, n)
    for f, (axis, value) in enumerate(((0, half), (0, -half), (1, half), (1, -half), (2, height))):
        pts[face == f, axis] = value
        normals[face == f, axis] = np.sign(value)
    return pts, normals


class ExactSource:
    """Exact correspondences of known points (+ Gaussian pixel noise): interest points are the
    visible points' projections, matches the points two views share. ``blind`` views see
    nothing (an image that cannot be registered)."""

    def __init__(self, points, normals, Ps, noise_px=0.1, seed=0, blind=(), no_epipolar=()):
        self.points, self.normals, self.Ps = points, normals, Ps
        self.noise, self.seed, self.blind, self.no_epipolar = noise_px, seed, set(blind), set(no_epipolar)
        self.ids = {}
        # a distinct patch per physical point: the same point scores 1, others ~N(0, 1/64)
        desc = np.random.default_rng(seed).normal(size=(len(points), 64)).astype(np.float32)
        self.desc = desc / np.linalg.norm(desc, axis=1, keepdims=True)

    def features(self, index, image):
        P = self.Ps[index]
        x = project(P, self.points)
        facing = np.einsum("ij,ij->i", self.normals, camera_center(P) - self.points) > 0
        inside = np.all((x > 10) & (x < np.array(SHAPE[::-1]) - 10), axis=1)
        ids = np.flatnonzero(facing & inside) if index not in self.blind else np.zeros(0, np.int64)
        self.ids[index] = ids
        xy = x[ids] + np.random.default_rng([self.seed, index]).normal(0, self.noise, (len(ids), 2))
        n = len(ids)
        return Features(xy, self.desc[ids], np.ones(n, bool), np.ones(n), SHAPE)

    def match(self, a, b, fa, fb, F, image_width):
        if F is None and b in self.no_epipolar:  # as on repeated patterns: no robust F
            return Matches.empty()
        _, ia, ib = np.intersect1d(self.ids[a], self.ids[b], return_indices=True)
        return Matches(ia, ib, np.ones(len(ia)))


def ring(n_views, step_deg=20.0, seed=0, n_points=3000, blind=(), no_epipolar=(), targets=None):
    rng = np.random.default_rng(seed)
    points, normals = box_surface(rng, n_points)
    targets = targets or {}
    Ps = [ring_camera(30.0 + i * step_deg, height=0.7, target=targets.get(i, (0.0, 0.0, 0.2)))[3]
          for i in range(n_views)]
    images = [np.full(SHAPE + (3,), i, np.uint8) for i in range(len(Ps))]  # distinct images (the pair check)
    names = [f"v{i}.png" for i in range(n_views)]
    return images, names, Ps, ExactSource(points, normals, Ps, blind=blind, no_epipolar=no_epipolar)


def centre_errors(recon, Ps):
    return np.array([np.linalg.norm(camera_center(v.P) - camera_center(P))
                     for v, P in zip(recon.views[2:], Ps[2:]) if v.registered])


def state(recon):
    """Everything an insertion may change, as comparable arrays."""
    views = [(v.P, v.features, v.point_of_feature.copy(), v.image, v.rotated_180, v.camera_model, v.zoomed,
              v.placement_flag) for v in recon.views]
    return (recon.points.copy(), recon.colors.copy(), recon.alive.copy(), recon.obs_view.copy(),
            recon.obs_feature.copy(), recon.obs_point.copy(), recon.obs_linked.copy(), views)


def assert_same_state(a, b):
    for x, y in zip(a[:7], b[:7]):
        np.testing.assert_array_equal(x, y)
    for va, vb in zip(a[7], b[7]):
        assert (va[0] is None) == (vb[0] is None)
        if va[0] is not None:
            np.testing.assert_array_equal(va[0], vb[0])
        assert va[1] is vb[1] and va[3] is vb[3]  # the same features and image objects
        np.testing.assert_array_equal(va[2], vb[2])
        assert va[4:] == vb[4:]




def as_if_placed_by(recon, k, found_by):
    """View k's history made to say that ``found_by`` placed it, its camera and links kept: a
    test playing a registration it did not run (the model has no public way to rewrite what
    placed a camera, and should not)."""
    from stereoseed.scene.camera_life import Registered

    recon.views[k]._record(Registered(found_by))


def walked(n_views, upto=None, cfg=None, **ring_kw):
    """A ring of ``n_views`` (:func:`ring`, ``ring_kw`` its options), the pair initialised and
    views 2 to ``upto`` (default: all) inserted, each registered: (recon, names, Ps, source)."""
    from stereoseed.config import Config
    from stereoseed.sfm.mapper import initialise, insert_view

    cfg = cfg or Config()
    images, names, Ps, source = ring(n_views, **ring_kw)
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    for k in range(2, (n_views - 1 if upto is None else upto) + 1):
        assert insert_view(recon, k, cfg, source)["status"] == "registered"
    return recon, names, Ps, source
