"""The walk through photos given in any order (issue #49, "photos in any order").

The incremental mapper needs its images in walk order: each one is placed from the one before
it. A folder in name order is often not that order (templeSparseRing's names are not its ring),
and every peer takes a folder of photos. The order is recovered from the images themselves: the
overlap of every pair, measured on thumbnails (SIFT features matched both ways, the matches a
robust fundamental matrix keeps), with the thumbnails' likeness where SIFT finds too little (a
dark, weakly textured object on a turntable), then a walk through that graph from the calibrated
pair (images 0 and 1 stay first: the calibration says which they are) that maximises the
strength of its steps (greedy, then improved by reversing parts of it, as for a travelling
salesman's path). A given order that is already a walk is kept; one the overlaps contradict is
replaced, and the caller says so.

Pure functions on arrays: the caller reads the thumbnails (:func:`thumbnail`).
"""
from __future__ import annotations

import logging
import cv2
import numpy as np

from stereoseed.matching.config import OrderingConfig

__all__ = ["OrderingConfig", "thumbnail", "overlaps", "likeness", "step_strengths", "best_walk", "too_many_to_order",
           "walk_order", "walk_strength"]

log = logging.getLogger(__name__)


def thumbnail(image: np.ndarray, long_side: int) -> np.ndarray:
    """A grey uint8 thumbnail (h, w) of ``image`` (H, W[, 3]) whose long side is at most
    ``long_side`` px (never enlarged)."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    scale = long_side / max(grey.shape[:2])
    if scale >= 1.0:
        return np.ascontiguousarray(grey)
    size = (max(1, round(grey.shape[1] * scale)), max(1, round(grey.shape[0] * scale)))
    return cv2.resize(grey, size, interpolation=cv2.INTER_AREA)


def overlaps(thumbnails: list[np.ndarray], cfg: OrderingConfig = OrderingConfig()) -> np.ndarray:
    """(N, N) int symmetric: for each pair of thumbnails (h, w) uint8, the number of SIFT matches
    (mutual best, ratio-tested) that a robust fundamental matrix keeps; 0 below
    ``cfg.min_inliers`` or without a robust F."""
    detector = cv2.SIFT_create(nfeatures=cfg.features)
    found = [detector.detectAndCompute(t, None) for t in thumbnails]
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    n = len(thumbnails)
    out = np.zeros((n, n), np.int64)
    for i in range(n):
        ki, di = found[i]
        for j in range(i + 1, n):
            kj, dj = found[j]
            if di is None or dj is None or len(ki) < 8 or len(kj) < 8:
                continue
            x1, x2 = _mutual_matches(matcher, ki, di, kj, dj, cfg.ratio)
            if len(x1) < max(8, cfg.min_inliers):
                continue
            _, mask = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, cfg.ransac_px, 0.999)
            inliers = 0 if mask is None else int(mask.sum())
            out[i, j] = out[j, i] = inliers if inliers >= cfg.min_inliers else 0
    return out


def likeness(thumbnails: list[np.ndarray], cfg: OrderingConfig = OrderingConfig()) -> np.ndarray:
    """(N, N) float symmetric in [0, 1]: how alike each pair of thumbnails (h, w) uint8 looks,
    the ZNCC of one's centre (a border of ``cfg.appearance_shift`` of its size left off) at its best
    place over the other, both at ``cfg.appearance_px`` and blurred by a pixel; the smaller of the
    two ways, 0 where either is flat or negative. The diagonal is 0."""
    small = [cv2.GaussianBlur(thumbnail(t, cfg.appearance_px).astype(np.float32), (0, 0), 1.0) for t in thumbnails]
    flat = [float(a.std()) == 0.0 for a in small]
    n = len(small)
    out = np.zeros((n, n))
    for i, a in enumerate(small):
        h, w = a.shape
        dy, dx = int(h * cfg.appearance_shift), int(w * cfg.appearance_shift)
        centre = a[dy:h - dy, dx:w - dx]
        if centre.size == 0 or float(centre.std()) == 0.0:
            continue
        for j, b in enumerate(small):
            if i == j or flat[j] or b.shape[0] < centre.shape[0] or b.shape[1] < centre.shape[1]:
                continue
            found = cv2.matchTemplate(b, centre, cv2.TM_CCOEFF_NORMED)
            out[i, j] = float(np.nanmax(found)) if np.isfinite(found).any() else 0.0
    return np.clip(np.minimum(out, out.T), 0.0, 1.0)


def step_strengths(overlap: np.ndarray, alike: np.ndarray, cfg: OrderingConfig = OrderingConfig()
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(strength (N, N) float: the SIFT overlap plus ``cfg.appearance_weight`` x the likeness,
    supported (N, N) bool: a step the images support, by an overlap or by a likeness of
    ``cfg.appearance_min``) from :func:`overlaps` and :func:`likeness`."""
    return overlap + cfg.appearance_weight * alike, (overlap > 0) | (alike >= cfg.appearance_min)


def _mutual_matches(matcher, ki, di, kj, dj, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (M, 2) float32 in both images of the matches that pass the ratio test and are each
    other's best both ways."""
    forward = {m[0].queryIdx: m[0].trainIdx for m in matcher.knnMatch(di, dj, k=2)
               if len(m) == 2 and m[0].distance < ratio * m[1].distance}
    backward = {m[0].queryIdx: m[0].trainIdx for m in matcher.knnMatch(dj, di, k=2)
                if len(m) == 2 and m[0].distance < ratio * m[1].distance}
    pairs = [(a, b) for a, b in forward.items() if backward.get(b) == a]
    x1 = np.float32([ki[a].pt for a, _ in pairs]).reshape(-1, 2)
    x2 = np.float32([kj[b].pt for _, b in pairs]).reshape(-1, 2)
    return x1, x2


def walk_strength(order: list[int], overlap: np.ndarray) -> tuple[float, float]:
    """(total overlap of consecutive images, the weakest step's) of ``order``."""
    steps = [overlap[a, b].item() for a, b in zip(order, order[1:])]
    return (sum(steps), min(steps)) if steps else (0, 0)


def best_walk(overlap: np.ndarray) -> list[int]:
    """An order of the N images of ``overlap`` (N, N) starting with 0, 1 (the calibrated pair)
    whose consecutive images overlap most: greedy from image 1 (the next image is the unused one
    overlapping the last most), then reversals of a part of the walk while one increases the total
    overlap (2-opt)."""
    n = len(overlap)
    order, unused = [0, 1], set(range(2, n))
    while unused:
        last = order[-1]
        nxt = max(sorted(unused), key=lambda u: (overlap[last, u], overlap[order, u].max()))
        order.append(nxt)
        unused.discard(nxt)
    improved = True
    while improved:  # at most n^2 reversals each pass; the walks are short
        improved = False
        for i in range(2, n - 1):
            for j in range(i + 1, n):
                # reversing order[i..j] changes the steps (i-1, i) and (j, j+1)
                a, b = order[i - 1], order[i]
                c, d = order[j], order[j + 1] if j + 1 < n else None
                before = overlap[a, b] + (overlap[c, d] if d is not None else 0)
                after = overlap[a, c] + (overlap[b, d] if d is not None else 0)
                if after > before:
                    order[i:j + 1] = order[i:j + 1][::-1]
                    improved = True
    return order


def too_many_to_order(n: int, cfg: OrderingConfig) -> bool:
    """Whether ``n`` images are more than every pair of them can be matched for
    (``OrderingConfig.max_images``); then says so: they run in the order given."""
    if n <= cfg.max_images:
        return False
    log.warning("%d images: more than OrderingConfig.max_images (%d) to order by their overlaps; run in the "
                "order given", n, cfg.max_images)
    return True


def walk_order(thumbnails: list[np.ndarray], cfg: OrderingConfig = OrderingConfig()
               ) -> tuple[list[int], str | None, str | None]:
    """The order to run the images of ``thumbnails`` in (their index list, 0 and 1 first), why
    it is not the given one (None: kept as given), and a doubt about a given order that was kept
    (None: none). A walk is taken only where the images support every step of it (each pair of
    consecutive thumbnails overlaps, or looks alike where SIFT finds too little:
    :func:`step_strengths`): a step with neither (a plain back of an object, a wide step) leaves
    the order to the user, since the mapper's motion prior may bridge it in the given order but
    not in one guessed around it."""
    n = len(thumbnails)
    given = list(range(n))
    if cfg.mode == "as-given" or n <= 3:
        return given, None, None
    if too_many_to_order(n, cfg):
        return given, None, None
    overlap = overlaps(thumbnails, cfg)
    strength, supported = step_strengths(overlap, likeness(thumbnails, cfg), cfg)
    found = best_walk(strength)
    (total, _), (found_total, _) = walk_strength(given, strength), walk_strength(found, strength)
    gaps = [i for i, (a, b) in enumerate(zip(given, given[1:])) if not supported[a, b]]
    steps = list(zip(found, found[1:]))
    found_gaps = sum(not supported[a, b] for a, b in steps)
    # A given order with a step nothing supports gives way to a walk SIFT supports throughout;
    # a walk resting on likeness somewhere must also be clearly stronger (photos of another
    # object of the same kind can look as alike as neighbours: 0.5-0.7 between the dino and the
    # temple), else the given order stays, with the doubt said
    by_likeness = any(overlap[a, b] == 0 for a, b in steps)
    better = found != given and ((bool(gaps) and not by_likeness) or found_total >= cfg.replace_factor * total)
    if better and not found_gaps:
        why = (f"a step of the given order has no overlap, every step of the order found has one"
               if gaps else f"consecutive images of the order found overlap by {found_total:.0f} in all, "
                            f"the given order's by {total:.0f}")
        return found, why, None
    doubt = None
    if better:
        doubt = (f"{len(gaps)} step(s) of the given order show no overlap (the first after image {gaps[0]}) and "
                 f"another order overlaps more ({found_total:.0f} against {total:.0f}); if the photos are not in "
                 f"walk order, list them in the order they were taken") if gaps else (
                 f"another order of the images overlaps more ({found_total:.0f} against {total:.0f}); if the photos "
                 f"are not in walk order, list them in the order they were taken")
    return given, None, doubt
