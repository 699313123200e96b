"""Quasi-dense match propagation for one image pair (Lhuillier & Quan, PAMI 2002).

Paper §4.4 / paper.md "Match propagation, precisely". Starting from sparse seed matches, a global
best-first search grows matches into their neighbourhoods:

1. Every pixel gets its 5x5 window mean and inverse norm once (``window_stats``), so that each
   ZNCC during the search is a single 25-term dot product, and a texture flag
   ``s(x) = max_{4-neighbours} |I(x+d) - I(x)| > min_texture``.
2. The rounded seeds, scored by their 5x5 ZNCC at integer positions, are accepted best first
   (a seed is dropped if ZNCC <= min_zncc or one of its pixels is already taken) and pushed on a
   max-heap keyed by ZNCC.
3. Pop the best match (x, x'). Candidates are all (u, u') with u in the (2r+1)^2 neighbourhood of
   x and u' within +-g px (disparity-gradient limit) of u + (x' - x): at most 225 for r=2, g=1.
   A candidate is kept if both pixels are unmatched and textured, ZNCC > min_zncc and, when F is
   given, u' lies within ``epipolar_band_px`` of the epipolar line F u. The kept candidates are
   accepted best first while both their pixels are still free; each accepted match is pushed.
4. Stop when the heap is empty. Every pixel is matched at most once in each image.

The search works on whole pixels. An optional sub-pixel step (ours, ``config.subpixel``) then
refines x2 of every match (x1 stays integer), by default with an affine-adapted ZNCC, else by a
quadratic fit of the 3x3 integer ZNCC surface (:mod:`stereoseed.matching.propagation.refine`; why and how
well: ``docs/propagation.md``).

Modules: the Numba kernels are in :mod:`stereoseed.matching.propagation._kernels`, the sub-pixel
refinement in :mod:`stereoseed.matching.propagation.refine`, the drawings in :mod:`stereoseed.output.visualize`;
this module holds the orchestration (:func:`propagate`, :class:`PropagationResult`).

Conventions are those of :mod:`stereoseed.geometry.projection`: pixel (0, 0) is the centre of the top-left
pixel, x right, y down; ``x2.T @ F @ x1 = 0``. Images are grey float in [0, 1] (uint8 and BGR
inputs are converted by :func:`stereoseed.features.image.to_gray` in float64, see :func:`_grey`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from stereoseed.matching.config import PropagationConfig
from stereoseed.errors import StereoseedError
from stereoseed.features.image import to_gray
from stereoseed.matching.propagation._kernels import propagate_kernel, window_stats, zncc_points
from stereoseed.threads import map_items
from stereoseed.matching.propagation.refine import refine_affine, refine_quadratic

__all__ = [
    "PropagationResult",
    "propagate",
    "texture_mask",
    "warm_up",
]


# --------------------------------------------------------------------------------------------
# Result
# --------------------------------------------------------------------------------------------


@dataclass
class PropagationResult:
    """Output of :func:`propagate`.

    Attributes:
        matches: (M, 4) float64, rows (x1, y1, x2, y2) in acceptance order (the accepted seeds
            come first). x1, y1 are integers; x2, y2 are integers too, or the refined sub-pixel
            position when ``subpixel`` is True (on the rows ``refine_rows`` chose, when given).
        scores: (M,) float32, the ZNCC of each match at its integer position (all > min_zncc).
        match_x, match_y: (H1, W1) int32, the integer pixel of image 2 matched to each pixel of
            image 1, -1 where unmatched.
        n_seeds_given: number of seed rows passed in.
        n_seeds_used: number of seeds that survived (valid window, ZNCC > min_zncc, pixels free);
            they are ``matches[:n_seeds_used]``.
        subpixel: whether x2, y2 were refined.
        subpixel_method: "affine", "quadratic" or "none".
        refined_by: (M,) int8, how each x2 was obtained: 0 integer, 1 quadratic fit of the
            3x3 ZNCC surface, 2 affine-adapted search (see :func:`propagate`).
        timings: seconds spent in each step: "prepare", "propagate", "subpixel", "total".
    """

    matches: np.ndarray
    scores: np.ndarray
    match_x: np.ndarray
    match_y: np.ndarray
    n_seeds_given: int
    n_seeds_used: int
    subpixel: bool
    subpixel_method: str = "none"
    refined_by: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int8))
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def n_matches(self) -> int:
        return int(self.matches.shape[0])

    @property
    def integer_matches(self) -> np.ndarray:
        """(M, 4) int32: (x1, y1, x2, y2) at the integer positions the search accepted."""
        x1 = self.matches[:, 0].astype(np.int32)
        y1 = self.matches[:, 1].astype(np.int32)
        return np.stack([x1, y1, self.match_x[y1, x1], self.match_y[y1, x1]], axis=1)

    def report(self) -> dict:
        """JSON-able summary (counts and timings)."""
        return {
            "n_seeds_given": self.n_seeds_given,
            "n_seeds_used": self.n_seeds_used,
            "n_matches": self.n_matches,
            "subpixel": self.subpixel,
            "subpixel_method": self.subpixel_method,
            "refined_by": {name: int(np.count_nonzero(self.refined_by == code))
                           for code, name in enumerate(("integer", "quadratic", "affine"))},
            "mean_score": float(self.scores.mean()) if self.n_matches else None,
            "timings": {k: float(v) for k, v in self.timings.items()},
        }


# --------------------------------------------------------------------------------------------
# Input helpers
# --------------------------------------------------------------------------------------------


def _grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float64 grey in [0, 1] by :func:`stereoseed.features.image.to_gray`; 8-bit colour is first
    reduced to 8-bit grey (cv2 rounds).

    Why the rounding: the dense stage's figures were measured with it; the unrounded grey
    changes the fused dense cloud by -10.6 % of its points (docs/propagation.md).
    """
    img = np.asarray(image)
    if img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    return to_gray(img, np.float64)


def texture_mask(image: np.ndarray, min_texture: float) -> np.ndarray:
    """LQ02 texture test: s(x) = max over the 4 neighbours of |I(x+d) - I(x)| > min_texture.

    image: (H, W) float in [0, 1] -> (H, W) bool. Neighbours outside the image are ignored.
    """
    img = np.asarray(image, dtype=np.float64)
    s = np.zeros_like(img)
    dx = np.abs(np.diff(img, axis=1))
    dy = np.abs(np.diff(img, axis=0))
    # each difference counts for both pixels it joins
    s[:, :-1] = np.maximum(s[:, :-1], dx)
    s[:, 1:] = np.maximum(s[:, 1:], dx)
    s[:-1, :] = np.maximum(s[:-1, :], dy)
    s[1:, :] = np.maximum(s[1:, :], dy)
    return s > min_texture


# --------------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------------


def propagate(
    img1: np.ndarray,
    img2: np.ndarray,
    seeds: np.ndarray,
    F: np.ndarray | None = None,
    config: PropagationConfig | None = None,
    *,
    seed_scores: np.ndarray | None = None,
    subpixel: bool | None = None,
    subpixel_method: str = "affine",
    refine_rows: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> PropagationResult:
    """Quasi-dense match propagation between two images (LQ02, paper §4.4).

    Args:
        img1: (H1, W1) grey float in [0, 1] (float32/float64; uint8 or BGR also accepted:
            converted by :func:`_grey`, float64 because the 25-term ZNCC sums need the
            precision on windows barely above the texture threshold).
        img2: (H2, W2) likewise; the sizes may differ.
        seeds: (S, 4) float64 (x1, y1, x2, y2) pixel coordinates of seed matches. They are
            rounded to whole pixels and re-scored by their ZNCC there; seeds with a window
            leaving an image, a ZNCC <= ``config.min_zncc`` or a pixel already claimed by a
            better seed are dropped. Seeds are not tested against the epipolar band: a wrong
            seed cannot grow anyway, because its neighbours must be in the band.
        F: (3, 3) fundamental matrix with ``x2.T F x1 = 0``, or None for no epipolar constraint.
        config: :class:`PropagationConfig` (window, min_zncc, min_texture, neighbourhood,
            disparity_gradient, epipolar_band_px, subpixel); defaults if None.
        seed_scores: optional (S,) scores of the seeds (e.g. their sparse-matching ZNCC). When
            given they decide which of several seeds claiming the same pixel wins (higher
            first); otherwise the recomputed ZNCC decides. The heap always uses the ZNCC.
        subpixel: overrides ``config.subpixel`` when not None.
        subpixel_method: how x2 is refined when sub-pixel refinement is on (x1 stays integer):

            * ``"quadratic"``: least-squares quadratic through the plain ZNCC at the 3x3
              integer shifts of x2; its maximum along the epipolar line of x1 when F is given
              (else its 2D maximum), offset clamped to +-1 px.
            * ``"affine"`` (default): two passes of an affine-adapted search. The local affine
              map x1 -> x2 is fitted by least squares on the matches of the 11x11
              neighbourhood (integer ones in pass 1, refined ones in pass 2); image 2's window
              is warped by it and its ZNCC maximised over points 0.5 px apart on the epipolar
              line within +-2 px of the affine prediction (without F: on a 0.5 px 2D grid),
              finished by a parabola. A result with warped ZNCC <= min_zncc is discarded;
              matches that no pass refined (fewer than 12 matched neighbours, or no warped
              ZNCC > min_zncc) get the quadratic fit. Needed on wide-baseline pairs, where the
              shear inside a 5x5 window moves the plain ZNCC peak by a pixel or more.
        refine_rows: when sub-pixel refinement is on, an optional function of the whole-pixel
            matches (M, 4) float64 and their scores (M,) float32 returning the rows (R,) int64
            (in [0, M)) to refine: a caller that reads a few hundred of tens of thousands of matches
            refines those alone (each comes out exactly as in a full refinement; the others
            keep whole pixels, ``refined_by`` 0). None: all rows.

    Returns:
        :class:`PropagationResult`. Empty (M = 0) when no seed survives, e.g. for empty seeds or
        an untextured image.
    """
    t0 = time.perf_counter()
    cfg = config if config is not None else PropagationConfig()
    do_subpixel = cfg.subpixel if subpixel is None else bool(subpixel)
    if subpixel_method not in ("affine", "quadratic"):
        raise StereoseedError(f"subpixel_method must be 'affine' or 'quadratic', got {subpixel_method!r}")
    if cfg.window < 1 or cfg.window % 2 == 0:
        raise StereoseedError(f"PropagationConfig.window must be odd and positive, got {cfg.window}")
    if cfg.neighbourhood < 0 or cfg.disparity_gradient < 0:
        raise StereoseedError("PropagationConfig.neighbourhood and disparity_gradient must be >= 0")
    half = cfg.window // 2

    I1 = _grey(img1)
    I2 = _grey(img2)
    H1, W1 = I1.shape
    H2, W2 = I2.shape
    seeds = np.asarray(seeds, dtype=np.float64)
    if seeds.size == 0:
        seeds = seeds.reshape(0, 4)
    if seeds.ndim != 2 or seeds.shape[1] != 4:
        raise StereoseedError(f"seeds must have shape (S, 4) (x1, y1, x2, y2), got {seeds.shape}")
    n_given = int(seeds.shape[0])
    if seed_scores is not None:
        seed_scores = np.asarray(seed_scores, dtype=np.float64).reshape(-1)
        if seed_scores.shape[0] != n_given:
            raise StereoseedError(f"seed_scores has {seed_scores.shape[0]} entries for {n_given} seeds")
    use_f = F is not None
    Fm = np.zeros((3, 3)) if F is None else np.ascontiguousarray(F, dtype=np.float64)
    if Fm.shape != (3, 3) or not np.all(np.isfinite(Fm)):
        raise StereoseedError(f"F must be a finite (3, 3) matrix, got shape {Fm.shape}")

    # per-pixel statistics; ok = may take part in a match (textured, full window, not flat)
    (mean1, inv1), (_, inv2) = map_items(lambda img: window_stats(img, half), (I1, I2))  # image 2's mean: unused
    ok1 = texture_mask(I1, cfg.min_texture) & (inv1 > 0.0)
    ok2 = texture_mask(I2, cfg.min_texture) & (inv2 > 0.0)

    # seeds: round to pixel centres, keep those inside both images, score, order
    finite = np.all(np.isfinite(seeds), axis=1)
    rs = np.zeros((n_given, 4), dtype=np.int64)
    rs[finite] = np.rint(seeds[finite]).astype(np.int64)
    inside = (finite & (rs[:, 0] >= 0) & (rs[:, 0] < W1) & (rs[:, 1] >= 0) & (rs[:, 1] < H1)
              & (rs[:, 2] >= 0) & (rs[:, 2] < W2) & (rs[:, 3] >= 0) & (rs[:, 3] < H2))
    zs = np.full(n_given, -1.0)
    if inside.any():
        zs[inside] = zncc_points(I1, mean1, inv1, I2, inv2, np.ascontiguousarray(rs[inside]), half)
    keep = inside & (zs > cfg.min_zncc)
    key = seed_scores if seed_scores is not None else zs
    idx = np.flatnonzero(keep)
    idx = idx[np.argsort(-key[idx], kind="stable")]
    t1 = time.perf_counter()

    x1, y1, x2, y2, sc, n_used, match_x, match_y = propagate_kernel(
        I1, mean1, inv1, ok1, I2, inv2, ok2,
        np.ascontiguousarray(rs[idx]), np.ascontiguousarray(zs[idx]),
        float(cfg.min_zncc), half, int(cfg.neighbourhood), int(cfg.disparity_gradient),
        use_f, Fm, float(cfg.epipolar_band_px))
    t2 = time.perf_counter()

    refined_by = np.zeros(x1.shape[0], dtype=np.int8)
    if do_subpixel and x1.shape[0] > 0:
        rows = None
        if refine_rows is not None:
            whole = np.stack([x1, y1, x2, y2], axis=1).astype(np.float64)
            rows = np.unique(np.asarray(refine_rows(whole, sc.astype(np.float32)), np.int64))
            if len(rows) and (rows[0] < 0 or rows[-1] >= len(whole)):
                raise StereoseedError(f"refine_rows gave rows outside [0, {len(whole)})")
        wanted = np.ones(x1.shape[0], bool)
        if rows is not None:
            wanted[:] = False
            wanted[rows] = True
        if subpixel_method == "affine":
            fx2, fy2, used = refine_affine(I1, mean1, inv1, I2, x1, y1, x2, y2, half, use_f, Fm,
                                            float(cfg.min_zncc), rows)
            used &= wanted  # a wanted row's neighbours were refined on the way: they stay whole
            fx2[~wanted], fy2[~wanted] = x2[~wanted], y2[~wanted]
            refined_by[used] = 2
            rest = np.flatnonzero(wanted & ~used)  # no affine fit or no warped ZNCC > min_zncc
        else:
            fx2, fy2 = x2.astype(np.float64), y2.astype(np.float64)
            rest = np.flatnonzero(wanted)
        if rest.size:
            fx2[rest], fy2[rest] = refine_quadratic(I1, mean1, inv1, I2, inv2, x1[rest], y1[rest],
                                                     x2[rest], y2[rest], half, use_f, Fm)
            refined_by[rest] = 1
    else:
        fx2, fy2 = x2.astype(np.float64), y2.astype(np.float64)
    t3 = time.perf_counter()

    matches = np.stack([x1.astype(np.float64), y1.astype(np.float64), fx2, fy2], axis=1)
    return PropagationResult(
        matches=matches.reshape(-1, 4),
        scores=sc.astype(np.float32),
        match_x=match_x,
        match_y=match_y,
        n_seeds_given=n_given,
        n_seeds_used=int(n_used),
        subpixel=do_subpixel,
        subpixel_method=subpixel_method if do_subpixel else "none",
        refined_by=refined_by,
        timings={"prepare": t1 - t0, "propagate": t2 - t1, "subpixel": t3 - t2, "total": t3 - t0},
    )


def warm_up() -> None:
    """Compile (or load from the Numba cache) every kernel on a tiny pair, so that timings of
    the first real call measure the work and not the JIT."""
    rng = np.random.default_rng(0)
    img = rng.random((32, 32))
    seeds = np.array([[12.0, 12.0, 12.0, 12.0]])
    F = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # horizontal lines
    for f in (F, None):
        for method in ("affine", "quadratic"):
            propagate(img, img, seeds, f, subpixel=True, subpixel_method=method)

