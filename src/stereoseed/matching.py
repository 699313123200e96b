"""ZNCC matching of interest points, epipolar filtering, robust F, and match chaining.

Paper §4.1 steps 3-4 and §4.2: each point of I_1 is matched to the point of I_2 with the best
normalised cross-correlation above a threshold; false matches are removed by the epipolar
constraint (F from the two calibrated cameras) or, when only the images are known, by a robust
estimate of F. The matches of consecutive pairs are chained to find the points of I_{k-1} seen in
both I_{k-2} and I_k (the paper's B_{k-1}).

Descriptors are zero-mean unit-norm patches (:mod:`stereoseed.features`), so the ZNCC of every
pair of points is one float32 matrix product; every test below is a mask on that matrix.

Three choices keep many matches without losing precision (measured on the synthetic box, see
tests/test_matching.py and benchmarks/bench_matching.py):

* with a known (or estimated) F, the epipolar band restricts the candidates *before* the best
  one is chosen ("guided matching", Hartley & Zisserman §11.6): a point whose true partner is
  not the global ZNCC maximum in a 2-D window is often the maximum along its epipolar band;
* a uniqueness test rejects a match whose best score is not clearly better than the best
  competitor (Lowe's ratio on the descriptor distance sqrt(2 - 2 ZNCC)). Competitors closer than
  ``unique_exclusion_px`` to the winner are ignored: they sample the same image structure and
  would reject good matches for being well localised rather than ambiguous. This is what catches
  repeated patterns such as the box's identical dark squares;
* when F is unknown, it is estimated robustly and the pair is matched again inside its band.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .camera import epipolar_distances
from .config import MatchingConfig
from .errors import StereoseedError
from .features import Features

__all__ = [
    "Matches",
    "zncc_matrix",
    "match_zncc",
    "filter_epipolar",
    "filter_fundamental_ransac",
    "match_pair",
    "chain",
    "draw_matches",
]

# Lowe's ratio on descriptor distances d = sqrt(2 - 2 ZNCC): the best candidate must be at most
# this fraction of the distance of the best competitor. 0.8 is Lowe's (IJCV 2004) choice.
DEFAULT_MAX_RATIO = 0.8
# Minimum number of inliers for a robust F to be trusted: F has 7 degrees of freedom and the
# minimal sample is 7-8 points, so a consensus barely above the minimal sample is not evidence.
DEFAULT_MIN_F_INLIERS = 15


@dataclass(frozen=True)
class Matches:
    """Correspondences between two feature arrays.

    idx1: (M,) int64 indices into the points of image 1; idx2: (M,) int64 into image 2;
    score: (M,) float64 ZNCC of each match (the resection chooses points by it).
    """

    idx1: np.ndarray
    idx2: np.ndarray
    score: np.ndarray

    def __post_init__(self) -> None:
        idx1 = np.asarray(self.idx1, dtype=np.int64).reshape(-1)
        idx2 = np.asarray(self.idx2, dtype=np.int64).reshape(-1)
        score = np.asarray(self.score, dtype=np.float64).reshape(-1)
        if not (idx1.shape == idx2.shape == score.shape):
            raise StereoseedError(
                f"Matches arrays differ in length: {idx1.shape}, {idx2.shape}, {score.shape}"
            )
        object.__setattr__(self, "idx1", idx1)
        object.__setattr__(self, "idx2", idx2)
        object.__setattr__(self, "score", score)

    @classmethod
    def empty(cls) -> "Matches":
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float64))

    def __len__(self) -> int:
        return int(self.idx1.shape[0])

    def subset(self, mask: np.ndarray) -> "Matches":
        """The matches selected by a (M,) bool mask or an array of positions."""
        mask = np.asarray(mask)
        return Matches(self.idx1[mask], self.idx2[mask], self.score[mask])

    def sorted_by_score(self) -> "Matches":
        """The same matches, best ZNCC first."""
        return self.subset(np.argsort(-self.score, kind="stable"))

    def points(self, kp1: "Features | np.ndarray", kp2: "Features | np.ndarray") -> tuple[np.ndarray, np.ndarray]:
        """Matched positions: x1 (M, 2) float64 in image 1, x2 (M, 2) float64 in image 2."""
        return _as_points(kp1)[self.idx1], _as_points(kp2)[self.idx2]


def _as_points(kp: "Features | np.ndarray") -> np.ndarray:
    pts = kp.points if isinstance(kp, Features) else kp
    return np.asarray(pts, dtype=np.float64).reshape(-1, 2)


def _warn(message: str) -> None:
    warnings.warn(message, RuntimeWarning, stacklevel=3)


def zncc_matrix(desc1: np.ndarray, desc2: np.ndarray) -> np.ndarray:
    """All ZNCC scores: (N1, D) x (N2, D) zero-mean unit-norm descriptors -> (N1, N2) float32."""
    return np.asarray(desc1, np.float32) @ np.asarray(desc2, np.float32).T


def _epipolar_band_mask(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, band_px: float) -> np.ndarray:
    """(N1, N2) bool: pairs within ``band_px`` of each other's epipolar line in both images.

    Same distance as :func:`stereoseed.camera.epipolar_distances` (max of both one-sided
    distances), for all pairs at once: the numerator |x2^T F x1| is shared, so the max distance
    is that numerator over the smaller of the two line normals.
    """
    F = np.asarray(F, np.float64)
    h1 = np.hstack([x1, np.ones((len(x1), 1))])
    h2 = np.hstack([x2, np.ones((len(x2), 1))])
    l2 = h1 @ F.T  # (N1, 3) epipolar lines in image 2
    l1 = h2 @ F  # (N2, 3) epipolar lines in image 1
    num = np.abs(l2 @ h2.T)  # (N1, N2) = |x2^T F x1|
    n2 = np.hypot(l2[:, 0], l2[:, 1])[:, None]
    n1 = np.hypot(l1[:, 0], l1[:, 1])[None, :]
    # num <= band * min(n1, n2)  <=>  max(num / n1, num / n2) <= band, without dividing by 0.
    return num <= band_px * np.minimum(n1, n2)


def _second_best(
    s: np.ndarray, best: np.ndarray, pts: np.ndarray, exclusion_px: float
) -> np.ndarray:
    """Best score per row of ``s`` (N, K, -inf = not a candidate) among columns farther than
    ``exclusion_px`` from the winning column ``best`` (N,); ``pts`` (K, 2) are the column points.
    Returns (N,) float32, -inf when there is no competitor.
    """
    d2 = ((pts[None, :, :] - pts[best][:, None, :]) ** 2).sum(axis=2)  # (N, K)
    near = d2 <= exclusion_px**2  # includes the winner itself
    return np.where(near, -np.inf, s).max(axis=1) if s.shape[1] else np.full(len(s), -np.inf)


def match_zncc(
    f1: Features,
    f2: Features,
    config: MatchingConfig = MatchingConfig(),
    image_width: float | None = None,
    *,
    F: np.ndarray | None = None,
    band_px: float | None = None,
    predicted: np.ndarray | None = None,
    prior_radius_px: float | None = None,
    max_ratio: float | None = DEFAULT_MAX_RATIO,
    unique_exclusion_px: float | None = None,
) -> Matches:
    """Match two feature sets by ZNCC.

    f1, f2: features of images 1 and 2 (descriptors of the same patch size).
    image_width: width (px) that scales ``config.search_radius``; default f2's image width.
    A pair (i, j) is a candidate when both descriptors are valid and x2_j lies within
    ``config.search_radius * image_width`` px of x1_i (of ``predicted[i]`` instead, (N1, 2), if
    given, within ``prior_radius_px``, default the same radius), and, if F (3, 3) is given,
    within ``band_px`` (default ``config.epipolar_band_px``) of the epipolar lines in both images.
    Each point of image 1 keeps its best candidate if its ZNCC exceeds ``config.min_zncc``, if it
    is also the best of the point of image 2 among its candidates (``config.mutual``), and if it
    passes the uniqueness test in both directions: ``sqrt(1 - best) < max_ratio *
    sqrt(1 - competitor)``, where the competitor is the best other candidate farther than
    ``unique_exclusion_px`` (default ``config.patch_size / 2``) from the winner. ``max_ratio``
    None (or >= 1) disables it.
    Returns Matches sorted by decreasing score; empty (with a warning) if either set is empty.
    """
    x1 = _as_points(f1)
    x2 = _as_points(f2)
    n1, n2 = len(x1), len(x2)
    if n1 == 0 or n2 == 0:
        _warn(f"no matches: {n1} and {n2} features")
        return Matches.empty()
    if f1.desc.shape[1] != f2.desc.shape[1]:
        raise StereoseedError(
            f"descriptor lengths differ ({f1.desc.shape[1]} vs {f2.desc.shape[1]}): "
            "extract both feature sets with the same patch_size"
        )
    v1 = np.flatnonzero(f1.valid)
    v2 = np.flatnonzero(f2.valid)
    if len(v1) == 0 or len(v2) == 0:
        _warn("no matches: no valid descriptor in one of the images")
        return Matches.empty()
    x1v, x2v = x1[v1], x2[v2]

    width = float(image_width if image_width is not None else f2.image_shape[1])
    radius = float(config.search_radius) * width
    centre = x1v
    if predicted is not None:
        predicted = np.asarray(predicted, np.float64).reshape(-1, 2)
        if len(predicted) != n1:
            raise StereoseedError(f"predicted has {len(predicted)} rows, f1 has {n1} points")
        centre = predicted[v1]
        radius = float(prior_radius_px) if prior_radius_px is not None else radius
    # Squared distances via |a|^2 + |b|^2 - 2ab: one (N1, N2) matrix product, no (N1, N2, 2) array.
    d2 = (
        (centre**2).sum(1)[:, None] + (x2v**2).sum(1)[None, :] - 2.0 * centre @ x2v.T
    )
    cand = d2 <= radius**2
    if F is not None:
        band = float(config.epipolar_band_px if band_px is None else band_px)
        cand &= _epipolar_band_mask(F, x1v, x2v, band)

    s = zncc_matrix(f1.desc[v1], f2.desc[v2])
    s = np.where(cand, s, np.float32(-np.inf))
    best2 = np.argmax(s, axis=1)  # (N1v,) best column of every row
    score = s[np.arange(len(v1)), best2]
    keep = score > config.min_zncc
    if config.mutual:
        best1 = np.argmax(s, axis=0)  # (N2v,) best row of every column
        keep &= best1[best2] == np.arange(len(v1))

    if max_ratio is not None and max_ratio < 1.0:
        excl = float(config.patch_size) / 2.0 if unique_exclusion_px is None else float(unique_exclusion_px)
        rows = np.flatnonzero(keep)
        if len(rows):
            cols = best2[rows]
            sub = s[rows]  # (K, N2v)
            comp2 = _second_best(sub, cols, x2v, excl)  # competitors in image 2
            comp1 = _second_best(s[:, cols].T, rows, x1v, excl)  # competitors in image 1
            comp = np.maximum(comp1, comp2).astype(np.float64)
            best = score[rows].astype(np.float64)
            # sqrt(1 - best) < r sqrt(1 - comp)  <=>  1 - best < r^2 (1 - comp); -inf passes.
            unique = (1.0 - best) < max_ratio**2 * (1.0 - comp)
            keep[rows[~unique]] = False

    rows = np.flatnonzero(keep)
    m = Matches(v1[rows], v2[best2[rows]], score[rows])
    return m.sorted_by_score()


def filter_epipolar(
    matches: Matches,
    kp1: "Features | np.ndarray",
    kp2: "Features | np.ndarray",
    F: np.ndarray,
    band_px: float,
) -> Matches:
    """Keep the matches within ``band_px`` of their epipolar lines in both images.

    F: (3, 3) with ``x2^T F x1 = 0``; kp1, kp2: Features or (N, 2) points.
    """
    if len(matches) == 0:
        return matches
    x1, x2 = matches.points(kp1, kp2)
    d = epipolar_distances(np.asarray(F, np.float64), x1, x2)
    return matches.subset(np.isfinite(d) & (d <= band_px))


def filter_fundamental_ransac(
    matches: Matches,
    kp1: "Features | np.ndarray",
    kp2: "Features | np.ndarray",
    config: MatchingConfig = MatchingConfig(),
    *,
    method: int = cv2.USAC_MAGSAC,
    min_inliers: int = DEFAULT_MIN_F_INLIERS,
) -> tuple[Matches, np.ndarray | None]:
    """Estimate F robustly and keep the matches consistent with it.

    method: an OpenCV robust method (``cv2.USAC_MAGSAC`` default, or ``cv2.FM_RANSAC``); threshold
    ``config.ransac_threshold_px``, confidence and iterations from ``config``; deterministic for a
    fixed ``config.seed``. Inliers are the matches within the threshold of their epipolar lines
    in both images (:func:`stereoseed.camera.epipolar_distances`).
    Returns (inlier Matches, F (3, 3) float64 of unit norm) or, with a RuntimeWarning, (empty
    Matches, None) when there are fewer than 8 matches, no estimate, or fewer than
    ``min_inliers`` inliers.
    """
    if len(matches) < 8:
        _warn(f"robust F needs at least 8 matches, got {len(matches)}")
        return Matches.empty(), None
    x1, x2 = matches.points(kp1, kp2)
    cv2.setRNGSeed(int(config.seed))
    try:
        F, _ = cv2.findFundamentalMat(
            x1,
            x2,
            method,
            float(config.ransac_threshold_px),
            float(config.ransac_confidence),
            int(config.ransac_max_iters),
        )
    except cv2.error as exc:  # degenerate configurations make some estimators throw
        _warn(f"robust F failed: {exc}")
        return Matches.empty(), None
    if F is None or F.shape[0] < 3 or not np.all(np.isfinite(F)) or np.linalg.norm(F[:3]) == 0:
        _warn("robust F found no model")
        return Matches.empty(), None
    F = np.asarray(F[:3], np.float64)
    F /= np.linalg.norm(F)
    d = epipolar_distances(F, x1, x2)
    inl = np.isfinite(d) & (d <= config.ransac_threshold_px)
    if inl.sum() < min_inliers:
        _warn(f"robust F has only {int(inl.sum())} inliers (< {min_inliers}): rejected")
        return Matches.empty(), None
    return matches.subset(inl), F


def match_pair(
    f1: Features,
    f2: Features,
    config: MatchingConfig = MatchingConfig(),
    F: np.ndarray | None = None,
    image_width: float | None = None,
    *,
    guided: bool = True,
    max_ratio: float | None = DEFAULT_MAX_RATIO,
    return_F: bool = False,
) -> "Matches | tuple[Matches, np.ndarray | None]":
    """Match two images: ZNCC + epipolar geometry.

    With F (3, 3) known (both cameras calibrated): candidates are restricted to the
    ``config.epipolar_band_px`` band before the best is chosen, then the band is checked again
    on the sub-pixel points (it already holds; kept as the contract of this function).
    Without F: unguided ZNCC matching, robust F (:func:`filter_fundamental_ransac`), and, if
    ``guided``, a second ZNCC pass inside the ``config.ransac_threshold_px`` band of the
    estimated F, whose result is checked against that F again.
    Returns Matches (sorted by decreasing score), and the F used/estimated if ``return_F``.
    """
    if F is not None:
        F = np.asarray(F, np.float64)
        m = match_zncc(f1, f2, config, image_width, F=F, max_ratio=max_ratio)
        m = filter_epipolar(m, f1, f2, F, config.epipolar_band_px)
        return (m, F) if return_F else m

    m = match_zncc(f1, f2, config, image_width, max_ratio=max_ratio)
    m, F_est = filter_fundamental_ransac(m, f1, f2, config)
    if guided and F_est is not None:
        band = float(config.ransac_threshold_px)
        mg = match_zncc(f1, f2, config, image_width, F=F_est, band_px=band, max_ratio=max_ratio)
        mg = filter_epipolar(mg, f1, f2, F_est, band)
        # Guided matching can only add evidence; never return fewer matches than the first pass.
        if len(mg) >= len(m):
            m = mg
    return (m, F_est) if return_F else m


def _first_by_key(key: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Positions of the best-scoring entry of each distinct key: (M,) -> (U,) int64."""
    order = np.argsort(-score, kind="stable")
    _, first = np.unique(key[order], return_index=True)
    return order[first]


def chain(m_ab: Matches, m_bc: Matches) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of image b matched both in a (by ``m_ab``) and in c (by ``m_bc``): the paper's B_{k-1}.

    Returns (ia, ib, ic), three (K,) int64 arrays: feature ``ib[k]`` of image b is matched to
    ``ia[k]`` of a and ``ic[k]`` of c; sorted by ib. If a point of b appears in several matches
    of one set (non-mutual matching), its best-scoring match is used. O(M log M), no Python loop.
    """
    if len(m_ab) == 0 or len(m_bc) == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty.copy(), empty.copy()
    ab = _first_by_key(m_ab.idx2, m_ab.score)
    bc = _first_by_key(m_bc.idx1, m_bc.score)
    # Lookup table from a feature index of b to its position in m_bc (-1: not matched in c).
    size = int(max(m_ab.idx2[ab].max(), m_bc.idx1[bc].max())) + 1
    pos_bc = np.full(size, -1, np.int64)
    pos_bc[m_bc.idx1[bc]] = bc
    ib_all = m_ab.idx2[ab]
    hit = pos_bc[ib_all] >= 0
    ab = ab[hit]
    ib = m_ab.idx2[ab]
    order = np.argsort(ib, kind="stable")
    ab, ib = ab[order], ib[order]
    return m_ab.idx1[ab], ib, m_bc.idx2[pos_bc[ib]]


def _to_bgr_u8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = np.clip(np.nan_to_num(img.astype(np.float64)) * (255.0 if img.max() <= 1.0 else 1.0), 0, 255)
        img = img.astype(np.uint8)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


def draw_matches(
    img1: np.ndarray,
    kp1: "Features | np.ndarray",
    img2: np.ndarray,
    kp2: "Features | np.ndarray",
    matches: Matches,
    path: "str | Path | None" = None,
    *,
    max_lines: int | None = None,
) -> np.ndarray:
    """Side-by-side image with a line per match (paper Fig. 10b), written as PNG if ``path``.

    img1, img2: grey or BGR images (uint8 or float in [0, 1]); kp1, kp2: Features or (N, 2).
    Line colour goes from red (lowest ZNCC) to green (highest). ``max_lines`` keeps the best.
    Returns the (max(H1, H2), W1 + W2, 3) uint8 BGR canvas.
    """
    a, b = _to_bgr_u8(img1), _to_bgr_u8(img2)
    h = max(a.shape[0], b.shape[0])
    canvas = np.zeros((h, a.shape[1] + b.shape[1], 3), np.uint8)
    canvas[: a.shape[0], : a.shape[1]] = a
    canvas[: b.shape[0], a.shape[1] :] = b
    m = matches.sorted_by_score()
    if max_lines is not None:
        m = m.subset(slice(0, max_lines))
    if len(m):
        x1, x2 = m.points(kp1, kp2)
        x2 = x2 + np.array([a.shape[1], 0.0])
        lo, hi = float(m.score.min()), float(m.score.max())
        t = (m.score - lo) / (hi - lo) if hi > lo else np.ones(len(m))
        shift = 4  # draw at 1/16 px so sub-pixel positions are honoured
        p1 = np.round(x1 * (1 << shift)).astype(np.int64)
        p2 = np.round(x2 * (1 << shift)).astype(np.int64)
        # Draw the weakest first so the best matches stay on top.
        for k in np.argsort(m.score):
            colour = (0, int(255 * t[k]), int(255 * (1 - t[k])))
            q1 = (int(p1[k, 0]), int(p1[k, 1]))
            q2 = (int(p2[k, 0]), int(p2[k, 1]))
            cv2.line(canvas, q1, q2, colour, 1, cv2.LINE_AA, shift)
            cv2.circle(canvas, q1, 2 << shift, colour, 1, cv2.LINE_AA, shift)
            cv2.circle(canvas, q2, 2 << shift, colour, 1, cv2.LINE_AA, shift)
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(path), canvas):
            raise StereoseedError(f"could not write {path}")
    return canvas
