"""Affine patch alignment: the localisation check and the sub-pixel refinement of matches.

Two Harris detections of one physical point drift apart once the viewpoint foreshortens the
surface, and the ZNCC of unaligned patches cannot tell. :func:`align_matches` finds, for each
match, where the patch of image 1 really lies in image 2 (affine Lucas-Kanade, a few hundredths
of a pixel); :func:`filter_localization` keeps the matches whose detection is there, and
:func:`refine_features` moves the matched points of image 2 onto it. :class:`PairCache` keeps
what matching one pair several times would compute again. The Numba kernels are in
:mod:`stereoseed.matching._alignment_kernel`.
"""
from __future__ import annotations

import threading
import weakref
from collections import OrderedDict

import cv2
import numpy as np

from stereoseed.arrays import unique
from stereoseed.matching.config import MatchingConfig
from stereoseed.errors import StereoseedError
from stereoseed.features.harris import DEFAULT_MIN_PATCH_STD, Features, describe
from stereoseed.threads import concat_chunks
from stereoseed.matching._alignment_kernel import align_kernel
from stereoseed.matching.containers import Alignment, Matches

__all__ = ["PairCache", "align_matches", "filter_localization", "refine_features", "release_gradients"]

# An alignment takes 30-80 us (13-16 iterations), handing a chunk to a pool thread 20-60 us: from
# 8 matches per chunk on, a thread saves more than it costs. Tracking aligns ~100 points per
# (view, reference) pair: with 64 per chunk, most of its calls stayed on one core
_ALIGNMENTS_PER_THREAD = 8


class PairCache:
    """What matching one pair several times (robust F, guided, relaxed, known F, then the
    sub-pixel refinement) would otherwise compute again: what :func:`~.zncc.match_zncc` keeps
    (``zncc``: descriptors at the other scales, the scored pairs of the search window) and the
    alignment of each (idx1, idx2) pair (``codes`` sorted, ``rows`` the matching
    :class:`Alignment` rows) for one
    set of alignment parameters (``params``: patch, iterations, tolerance; the relaxed
    configuration shares them). Valid for the two Features objects it was made for (identity).
    """

    def __init__(self, f1: Features, f2: Features):
        self.f1, self.f2 = f1, f2
        self.zncc: dict[tuple, object] = {}
        self.params: tuple | None = None
        self.codes = np.zeros(0, np.int64)
        self.rows = Alignment(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0), np.zeros(0, bool))

    def covers(self, f1: Features, f2: Features) -> bool:
        return f1 is self.f1 and f2 is self.f2

    def lookup(self, codes: np.ndarray) -> np.ndarray:
        """(M,) row of each code in the cache, -1 where absent."""
        pos = np.minimum(np.searchsorted(self.codes, codes), max(len(self.codes) - 1, 0))
        hit = (self.codes[pos] == codes) if len(self.codes) else np.zeros(len(codes), bool)
        return np.where(hit, pos, -1)

    def add(self, codes: np.ndarray, al: Alignment) -> None:
        codes = np.concatenate([self.codes, codes])
        order = np.argsort(codes, kind="stable")
        r = self.rows
        self.codes = codes[order]
        self.rows = Alignment(np.concatenate([r.x2, al.x2])[order], np.concatenate([r.affine, al.affine])[order],
                              np.concatenate([r.zncc, al.zncc])[order], np.concatenate([r.converged, al.converged])[order])


# The gradients of the last few reference images: one image is aligned against its neighbours,
# tracked into later views and checked again, each time with the same Sobel images
_GRADIENTS: OrderedDict[int, tuple] = OrderedDict()
_GRADIENTS_KEPT = 8
# and at most this many bytes of them: eight 24-megapixel images' would be 1.5 GB
_GRADIENT_BYTES = 512 << 20
# re-entrant: the finalizer that drops an image's entry may run inside a locked section (a
# garbage collection there freeing a grey image)
_gradients_lock = threading.RLock()


def _with_gradients(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A grey image as float32 and its Sobel x and y derivatives (scaled to grey levels per
    pixel), from the cache while ``gray`` itself is alive (held by a weak reference: an id is
    only unique among living objects; the entry goes when the image does). Grey images are
    never changed in place (Features.gray is the image the points were found in)."""
    key = id(gray)
    g = np.ascontiguousarray(gray, np.float32)  # gray itself when it already is
    with _gradients_lock:
        hit = _GRADIENTS.get(key)
        if hit is not None and hit[0]() is gray:
            _GRADIENTS.move_to_end(key)
            return g, hit[1], hit[2]
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    with _gradients_lock:  # not the image: a view that lets its image go frees it
        _GRADIENTS[key] = (weakref.ref(gray), gx, gy)
        while len(_GRADIENTS) > 1 and (len(_GRADIENTS) > _GRADIENTS_KEPT or sum(
                e[1].nbytes + e[2].nbytes for e in _GRADIENTS.values()) > _GRADIENT_BYTES):
            _GRADIENTS.popitem(last=False)
    weakref.finalize(gray, _forget_gradients, key, gx)  # and its gradients with it
    return g, gx, gy


def release_gradients() -> None:
    """Drop every cached gradient image: a finished run aligns nothing more, and at 3072 x 2048
    the cache's eight images hold 400 MB the dense stage can use."""
    with _gradients_lock:
        _GRADIENTS.clear()


def _forget_gradients(key: int, gx: np.ndarray) -> None:
    with _gradients_lock:
        hit = _GRADIENTS.get(key)
        if hit is not None and hit[1] is gx:  # not a newer image's entry under a reused id
            del _GRADIENTS[key]


def align_matches(
    f1: Features,
    f2: Features,
    matches: Matches,
    config: MatchingConfig,
    *,
    cache: PairCache | None = None,
) -> Alignment:
    """Align the patch of every match by affine Lucas-Kanade on normalised patches.

    For each of the M matches the (P, P) patch of image 1 centred on x1 (P =
    ``config.align_patch_size``, offsets u) is compared with image 2 sampled at ``A u + t`` (t
    starting at the detected x2, A at the identity). The residual is the difference of the
    zero-mean unit-norm patches, so gain and bias changes do not matter. Inverse-compositional
    Gauss-Newton (Baker & Matthews, IJCV 2004): the Jacobian and Hessian come from the template
    once, each iteration only samples image 2. The first iterations move t only; every step is
    capped at 1 px and 0.1 of linear change (a trust region: far from the optimum the affine
    terms of the linearisation overshoot); iterations (at most ``config.align_max_iters``) stop
    when t moves less than ``config.align_tol_px``. Needs the grey images (``Features.gray``,
    set by extract_features).

    Returns an :class:`Alignment` (M rows). A match does not converge if a patch leaves its
    image, is flat, or the warp degenerates (singular values outside [1/4, 4], drift beyond
    P/2 px). With a ``cache`` made for (f1, f2), pairs aligned before are not aligned again.
    """
    if f1.gray is None or f2.gray is None:
        raise StereoseedError(
            "align_matches needs the grey images: build the Features with extract_features"
        )
    patch_size, max_iters, tol_px = config.align_patch_size, config.align_max_iters, config.align_tol_px
    params = (patch_size, max_iters, tol_px)
    if cache is not None and cache.covers(f1, f2) and cache.params in (None, params):
        cache.params = params
        stride = max(len(f2), 1)  # a pair (idx1, idx2) is coded idx1 * stride + idx2
        codes = matches.idx1.astype(np.int64) * stride + matches.idx2
        missing = unique(codes[cache.lookup(codes) < 0])
        if len(missing):
            todo = Matches(missing // stride, missing % stride, np.zeros(len(missing)))
            cache.add(missing, align_matches(f1, f2, todo, config))
        rows = cache.lookup(codes)
        r = cache.rows
        return Alignment(r.x2[rows], r.affine[rows], r.zncc[rows], r.converged[rows])
    x1, x2 = matches.points(f1, f2)
    g1, gx, gy = _with_gradients(f1.gray)
    g2 = np.ascontiguousarray(f2.gray, np.float32)
    x1 = np.ascontiguousarray(x1, np.float64)
    x2 = np.ascontiguousarray(x2, np.float64)
    args = (patch_size // 2, int(max_iters), float(tol_px), float(DEFAULT_MIN_PATCH_STD * patch_size))
    return Alignment(*concat_chunks(lambda a, b: align_kernel(g1, gx, gy, g2, x1[a:b], x2[a:b], *args),
                                    len(x1), _ALIGNMENTS_PER_THREAD))


def filter_localization(
    matches: Matches,
    f1: Features,
    f2: Features,
    config: MatchingConfig,
    *,
    cache: PairCache | None = None,
) -> Matches:
    """Keep the matches whose two detections are the same point, scored by aligned ZNCC.

    Aligns every match (:func:`align_matches`) and keeps those that converged, whose aligned
    position lies within ``config.max_shift_px`` of the detected point of image 2, and whose
    aligned ZNCC exceeds ``config.min_aligned_zncc`` (``config.relaxed()`` for the relaxed
    check). Returns the kept matches, scored by their aligned ZNCC, best first.
    """
    if len(matches) == 0:
        return matches
    al = align_matches(f1, f2, matches, config, cache=cache)
    keep = al.converged & (al.shift(f2, matches) <= config.max_shift_px) & (al.zncc > config.min_aligned_zncc)
    return Matches(matches.idx1[keep], matches.idx2[keep], al.zncc[keep]).sorted_by_score()


def refine_features(
    f1: Features,
    f2: Features,
    matches: Matches,
    config: MatchingConfig,
    *,
    cache: PairCache | None = None,
) -> Features:
    """Copy of ``f2`` whose matched points sit where their partners of image 1 are, sub-pixel.

    Each matched point of image 2 moves to the aligned position of its partner
    (:func:`align_matches`); its descriptor is recomputed there. Points that are unmatched,
    matched more than once, or whose alignment did not converge keep their detected position.
    Indices are unchanged, so ``matches`` stays valid for the returned features.

    Why: triangulation and resection then see consistent positions, and a track followed pair
    after pair (a -> b -> c, refining b's features against a, then c's against b) carries the
    position of the same physical point instead of accumulating detector noise.
    """
    if len(matches) == 0:
        return f2
    al = align_matches(f1, f2, matches, config, cache=cache)
    counts = np.bincount(matches.idx2, minlength=len(f2))
    move = al.converged & (counts[matches.idx2] == 1)
    points = f2.points.copy()
    points[matches.idx2[move]] = al.x2[move]
    desc, valid = f2.desc.copy(), f2.valid.copy()
    if f2.gray is not None and move.any():
        idx = matches.idx2[move]
        desc[idx], valid[idx] = describe(f2.gray, points[idx], f2.patch_size)
    return Features(points, desc, valid, f2.response, f2.image_shape, f2.gray)
