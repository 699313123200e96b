"""Sub-pixel refinement of the propagation's whole-pixel matches (x1 stays integer, x2 moves).

Two methods (see :func:`stereoseed.matching.propagation.core.propagate` and ``docs/propagation.md``):

* :func:`refine_quadratic`: least-squares quadratic through the plain ZNCC at the 3x3 integer
  shifts of x2, maximised along the epipolar line of x1 when F is given.
* :func:`refine_affine`: the local affine map x1 -> x2 is fitted on the neighbouring matches,
  image 2's window is warped by it and its ZNCC maximised along the epipolar line.

Images are (H, W) float64 grey levels in [0, 1]; matches are (M,) int32 arrays x1, y1, x2, y2.
"""
from __future__ import annotations

import cv2
import numpy as np
from numba import njit

from stereoseed.matching.propagation._kernels import FASTMATH, dot_window, epipolar_line, load_centred
from stereoseed.threads import concat_chunks


@njit(cache=True, nogil=True)
def refine_quadratic(I1, mean1, inv1, I2, inv2, mx1, my1, mx2, my2, half, use_f, F):
    """Sub-pixel x2 for each integer match by a quadratic fit of the 3x3 ZNCC surface.

    The ZNCC at the 9 integer shifts of x2 is fitted by least squares with
    q(o) = a + b ox + c oy + d ox^2 + e ox oy + g oy^2 (closed form on a 3x3 grid). Without F
    the offset is the maximum of q when q is concave (else the 1D parabola maxima of the
    central row/column, where concave); with F it is the maximum of q along the epipolar line
    of x1 (starting from the foot of the perpendicular from x2), which ignores the ill-defined
    direction along a 1D texture. Offsets are clamped to +-1 px (along the line with F).
    A window of the 3x3 grid leaving image 2 or flat leaves x2 integer (still projected on the
    line with F, which can only move it closer to the true match).
    Returns x2, y2 (M,) float64.
    """
    M = mx1.shape[0]
    H2, W2 = I2.shape
    ox2 = np.empty(M)
    oy2 = np.empty(M)
    buf = np.empty((2 * half + 1) * (2 * half + 1))
    z = np.empty((3, 3))
    for i in range(M):
        x1 = mx1[i]
        y1 = my1[i]
        x2 = mx2[i]
        y2 = my2[i]
        ox = 0.0
        oy = 0.0
        valid = x2 - 1 >= 0 and y2 - 1 >= 0 and x2 + 1 < W2 and y2 + 1 < H2
        if valid:
            load_centred(I1, mean1, x1, y1, half, buf)
            for sy in range(-1, 2):
                for sx in range(-1, 2):
                    iv = inv2[y2 + sy, x2 + sx]
                    if iv == 0.0:  # flat, or its window leaves image 2: reading it would run off the
                        valid = False  # array (a segfault where the image ends a memory mapping)
                    else:
                        z[sy + 1, sx + 1] = inv1[y1, x1] * iv * dot_window(buf, I2, x2 + sx, y2 + sy, half)
        # quadratic coefficients on the 3x3 grid (orthogonal-polynomial least squares)
        b = c = d = e = g = 0.0
        if valid:
            colm = z[0, 0] + z[1, 0] + z[2, 0]  # column sums, x = -1, 0, +1
            col0 = z[0, 1] + z[1, 1] + z[2, 1]
            colp = z[0, 2] + z[1, 2] + z[2, 2]
            rowm = z[0, 0] + z[0, 1] + z[0, 2]  # row sums, y = -1, 0, +1
            row0 = z[1, 0] + z[1, 1] + z[1, 2]
            rowp = z[2, 0] + z[2, 1] + z[2, 2]
            b = (colp - colm) / 6.0
            c = (rowp - rowm) / 6.0
            d = (colp + colm - 2.0 * col0) / 6.0
            g = (rowp + rowm - 2.0 * row0) / 6.0
            e = (z[2, 2] - z[2, 0] - z[0, 2] + z[0, 0]) / 4.0
        if use_f:
            la, lb, lc, nrm = epipolar_line(F, x1, y1)
            if nrm > 0.0:
                r = la * x2 + lb * y2 + lc  # signed distance of x2 to the line
                px = -r * la  # foot of the perpendicular, as an offset from x2
                py = -r * lb
                ux = -lb  # unit direction of the line
                uy = la
                if valid:
                    gx = b + 2.0 * d * px + e * py  # gradient of q at the foot
                    gy = c + e * px + 2.0 * g * py
                    curv = 2.0 * d * ux * ux + 2.0 * e * ux * uy + 2.0 * g * uy * uy
                    t = 0.0
                    if curv < 0.0:
                        t = -(gx * ux + gy * uy) / curv
                        t = min(1.0, max(-1.0, t))
                    px += t * ux
                    py += t * uy
                ox = px
                oy = py
        elif valid:
            det = 4.0 * d * g - e * e
            if d < 0.0 and det > 0.0:  # concave: the stationary point is the maximum
                ox = (-2.0 * g * b + e * c) / det
                oy = (e * b - 2.0 * d * c) / det
            else:  # saddle or flat: 1D parabolas through the centre, where they are concave
                crx = z[1, 2] + z[1, 0] - 2.0 * z[1, 1]
                cry = z[2, 1] + z[0, 1] - 2.0 * z[1, 1]
                if crx < 0.0:
                    ox = -(z[1, 2] - z[1, 0]) / (2.0 * crx)
                if cry < 0.0:
                    oy = -(z[2, 1] - z[0, 1]) / (2.0 * cry)
            ox = min(1.0, max(-1.0, ox))
            oy = min(1.0, max(-1.0, oy))
        ox2[i] = x2 + ox
        oy2[i] = y2 + oy
    return ox2, oy2


# Affine-adapted refinement (ours): at wide baselines the map x1 -> x2 shears a 5x5 window enough
# to move the plain ZNCC peak by a pixel, and the neighbouring matches tell the local affine map
# (figures in docs/propagation.md).
_AFFINE_RADIUS = 5  # the local affine map is fitted on the matches of an 11x11 neighbourhood
_AFFINE_MIN_MATCHES = 12  # fewer neighbours (12 of 121) give too wobbly a Jacobian
_SEARCH_PX = 2.0  # half-length of the search around the affine prediction
_SEARCH_STEP = 0.5  # sampling step of the search; a parabola through the best 3 finishes it
_AFFINE_PASSES = 2  # pass 2 re-fits the affine maps on the pass-1 positions
_INVALID = -2.0  # _warped_zncc's value for a window leaving image 2 or flat
_UNSEEN = -3.0  # search-grid cell not evaluated yet
_MATCHES_PER_THREAD = 2048  # a match's search takes ~2 us: fewer per thread cost more than they save
# image 1's pixels whose affine fields are held at once (8 MB a field): the fit's 12 filters keep
# their speed, and a 24-megapixel image's fields are not all in memory together
_BAND_PIXELS = 1 << 20


def _fit_system(matched, x1, y1, radius, min_count):
    """The least-squares system of each match's local affine fit (:func:`_affine_fields`):
    it depends only on which pixels of image 1 are matched (each band's pass builds its own).

    matched: (H1, W1) bool; x1, y1: (M,) int32 the matched pixels to fit at. Returns their flat
    indices ``at`` (M,) int64, the six cofactors (c00, c01, c02, c11, c12, c22), each (M,), of each
    symmetric 3x3 normal matrix [[s0 s1 s2] [s1 s11 s12] [s2 s12 s22]] (s_ab = sum over the
    matched q of the window of (qx - px)^a (qy - py)^b) and its determinant (M,), NaN where
    fewer than min_count neighbours are matched or they lie (nearly) on a line."""
    W = matched.shape[1]
    at = y1.astype(np.int64) * W + x1  # flat indices: one gather per filtered image, 5x faster than [y1, x1]
    mf = matched.astype(np.float64)
    k0, k1, k2 = _window_kernels(radius)
    s0 = _filter_at(mf, at, k0, k0)
    s1 = _filter_at(mf, at, k1, k0)
    s2 = _filter_at(mf, at, k0, k1)
    s11 = _filter_at(mf, at, k2, k0)
    s12 = _filter_at(mf, at, k1, k1)
    s22 = _filter_at(mf, at, k0, k2)
    c00 = s11 * s22 - s12 * s12
    c01 = s2 * s12 - s1 * s22
    c02 = s1 * s12 - s2 * s11
    c11 = s0 * s22 - s2 * s2
    c12 = s1 * s2 - s0 * s12
    c22 = s0 * s11 - s1 * s1
    det = s0 * c00 + s1 * c01 + s2 * c02
    ok = (s0 >= min_count - 0.5) & (det > 1e-9 * s0 * s11 * s22)
    return at, (c00, c01, c02, c11, c12, c22), np.where(ok, det, np.nan)


def _window_kernels(radius):
    """The separable kernels 1, o, o^2 over the window offsets o in [-radius, radius]."""
    o = np.arange(-radius, radius + 1, dtype=np.float64)
    return np.ones_like(o), o, o * o


def _filter_at(img, at, kx, ky):
    """The correlation out(p) = sum_o kx(ox) ky(oy) img(p + o) (zero outside the image) at the
    flat pixel indices ``at``."""
    return cv2.sepFilter2D(img, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_CONSTANT).reshape(-1)[at]


def _affine_fields(fx, fy, x1, y1, radius, system, top=0):
    """Local affine map x1 -> x2 around each match, fitted on its neighbours' matches.

    fx, fy: (B, W1) float64 positions in image 2 of the matched pixels of a band of B rows of
    image 1 (rows top to top + B - 1), NaN where unmatched (overwritten: the disparities, each
    position less its own pixel's, in one subtraction as over the whole image); x1, y1: (M,)
    int32 the matched pixels (image 1's rows), system:
    :func:`_fit_system` of the band's matched pixels at them. For each match p, fits by least squares
    x2(q) = c + J (q - p) over the matched q of the (2 radius + 1)^2 window of p.
    Returns (M, 6) float64 (cx, cy, J00, J01, J10, J11), c being the fitted x2 at p itself;
    NaN rows where the system refuses the fit.

    The fit is written on the disparity d(q) = x2(q) - q, which is small, and every window sum
    is a separable filter of a per-pixel image (sum_q m(q) (qx - px)^a (qy - py)^b d(q)), so
    all the band's matches are fitted at once at the cost of 12 separable filters of its size.
    Plain least squares: a robust re-weighting costs 3x the time for no measurable gain
    (docs/propagation.md).
    """
    H, W = fx.shape
    # the disparities in place of the positions (the caller's fields are spent): at 3072 x 2048
    # a pixel grid and two new fields would be 300 MB more
    unmatched = ~np.isfinite(fx)
    dx = np.subtract(fx, np.arange(W, dtype=np.float64)[None, :], out=fx)
    dy = np.subtract(fy, np.arange(top, top + H, dtype=np.float64)[:, None], out=fy)
    dx[unmatched] = 0.0
    dy[unmatched] = 0.0
    del unmatched
    k0, k1, _ = _window_kernels(radius)
    at, (c00, c01, c02, c11, c12, c22), det = system
    out = np.empty((x1.shape[0], 6))
    for row, d in enumerate((dx, dy)):
        b0, b1, b2 = _filter_at(d, at, k0, k0), _filter_at(d, at, k1, k0), _filter_at(d, at, k0, k1)
        out[:, row] = (c00 * b0 + c01 * b1 + c02 * b2) / det + (x1 if row == 0 else y1)
        out[:, 2 + 2 * row] = (c01 * b0 + c11 * b1 + c12 * b2) / det + (1.0 if row == 0 else 0.0)
        out[:, 3 + 2 * row] = (c02 * b0 + c12 * b1 + c22 * b2) / det + (0.0 if row == 0 else 1.0)
    return out


@njit(cache=True, fastmath=FASTMATH)
def _warped_zncc(buf, norm1, I2, cx, cy, jxx, jxy, jyx, jyy, half):
    """ZNCC of a centred image-1 window (buf, its norm norm1) against image 2 sampled
    bilinearly at cx + J (wx, wy) for the window offsets (wx, wy). _INVALID (-2) if the warped
    window leaves image 2 or is flat.

    The bilinear sample is written inline, not image.sample_bilinear: the window is checked
    inside once (no clamping needed) and this kernel's "contract" flag fuses its multiply-adds,
    so a shared non-fastmath call would change the dense results' last bits."""
    H2, W2 = I2.shape
    ex = (abs(jxx) + abs(jxy)) * half
    ey = (abs(jyx) + abs(jyy)) * half
    # strict upper bound keeps x0 + 1 inside the image for the bilinear weights
    if cx - ex < 0.0 or cy - ey < 0.0 or cx + ex >= W2 - 1 or cy + ey >= H2 - 1:
        return _INVALID
    n = (2 * half + 1) * (2 * half + 1)
    sab = 0.0
    sb = 0.0
    sbb = 0.0
    k = 0
    for wy in range(-half, half + 1):
        for wx in range(-half, half + 1):
            x = cx + jxx * wx + jxy * wy
            y = cy + jyx * wx + jyy * wy
            x0 = int(x)  # x >= 0 here, so int() is floor
            y0 = int(y)
            ax = x - x0
            ay = y - y0
            v = ((I2[y0, x0] * (1.0 - ax) + I2[y0, x0 + 1] * ax) * (1.0 - ay)
                 + (I2[y0 + 1, x0] * (1.0 - ax) + I2[y0 + 1, x0 + 1] * ax) * ay)
            sab += buf[k] * v  # buf sums to zero: no need to centre v
            sb += v
            sbb += v * v
            k += 1
    var = sbb - sb * sb / n
    if not var > 1e-12:
        return _INVALID
    return sab / (norm1 * np.sqrt(var))


@njit(cache=True, nogil=True)
def _refine_affine_pass(I1, mean1, inv1, I2, x1s, y1s, aff, use_f, F, half, search_px, step,
                        min_zncc, prev_x, prev_y):
    """One pass of the affine-adapted refinement.

    For each match with a valid affine row aff[i] = (cx, cy, J) (see _affine_fields): with F,
    the prediction c is projected on the epipolar line of x1 and the warped ZNCC is maximised
    over the points of the line every ``step`` px within +-search_px of it (hill climbing from
    c), then a parabola through the best sample and its two neighbours gives the maximum.
    Without F the same climb runs on the 2D grid of step ``step`` within +-search_px of c
    (8-neighbourhood) and a 2D quadratic is fitted on the 3x3 samples around the best.
    The new position is kept if its warped ZNCC > min_zncc; otherwise the previous estimate
    (prev_x, prev_y) stays. It is deliberately not tied to the integer match: where the
    integer match is grossly off (a disparity gradient above the +-1 px limit, on the test
    scene's box top), the affine prediction from the neighbours is what brings it back.
    Returns x2, y2 (M,) float64 and used (M,) bool (True where this pass set the position).
    """
    M = x1s.shape[0]
    n = (2 * half + 1) * (2 * half + 1)
    out_x = prev_x.copy()
    out_y = prev_y.copy()
    used = np.zeros(M, np.bool_)
    buf = np.empty(n)
    ns = int(np.round(search_px / step))
    zs = np.empty(2 * ns + 1)
    zg = np.empty((2 * ns + 1, 2 * ns + 1))
    for i in range(M):
        if aff[i, 0] != aff[i, 0]:
            continue
        px = x1s[i]
        py = y1s[i]
        if inv1[py, px] == 0.0:
            continue
        load_centred(I1, mean1, px, py, half, buf)
        norm1 = 1.0 / inv1[py, px]
        cx = aff[i, 0]
        cy = aff[i, 1]
        jxx = aff[i, 2]
        jxy = aff[i, 3]
        jyx = aff[i, 4]
        jyy = aff[i, 5]
        det_j = jxx * jyy - jxy * jyx
        # a visible surface maps with det J > 0; outside [0.1, 10] the fit mixes two surfaces
        if not 0.1 < det_j < 10.0:
            continue
        best = _INVALID
        rx = cx
        ry = cy
        if use_f:
            la, lb, lc, nrm = epipolar_line(F, px, py)
            if nrm == 0.0:
                continue
            r = la * cx + lb * cy + lc
            cx -= r * la  # foot of the perpendicular: the search runs on the line itself
            cy -= r * lb
            ux = -lb
            uy = la
            # hill climbing from the prediction: 3-4 evaluations instead of 9, same accuracy as
            # an exhaustive scan (docs/propagation.md)
            for j in range(2 * ns + 1):
                zs[j] = _UNSEEN
            bj = ns
            zs[bj] = _warped_zncc(buf, norm1, I2, cx, cy, jxx, jxy, jyx, jyy, half)
            while True:
                nb = bj
                for jj in (bj - 1, bj + 1):
                    if jj < 0 or jj > 2 * ns:
                        continue
                    if zs[jj] == _UNSEEN:
                        s = (jj - ns) * step
                        zs[jj] = _warped_zncc(buf, norm1, I2, cx + s * ux, cy + s * uy,
                                              jxx, jxy, jyx, jyy, half)
                    if zs[jj] > zs[nb]:
                        nb = jj
                if nb == bj:
                    break
                bj = nb
            best = zs[bj]
            off = 0.0
            if 0 < bj < 2 * ns and zs[bj - 1] > _INVALID and zs[bj + 1] > _INVALID:
                curv = zs[bj - 1] + zs[bj + 1] - 2.0 * zs[bj]
                if curv < 0.0:
                    off = -(zs[bj + 1] - zs[bj - 1]) / (2.0 * curv)
            s = (bj - ns + off) * step
            rx = cx + s * ux
            ry = cy + s * uy
        else:
            # 2D hill climbing on the step grid within +-search_px, 8-neighbourhood
            for j in range(2 * ns + 1):
                for k in range(2 * ns + 1):
                    zg[j, k] = _UNSEEN
            bj = ns
            bk = ns
            zg[bj, bk] = _warped_zncc(buf, norm1, I2, cx, cy, jxx, jxy, jyx, jyy, half)
            while True:
                nj = bj
                nk = bk
                for j in range(max(bj - 1, 0), min(bj + 2, 2 * ns + 1)):
                    for k in range(max(bk - 1, 0), min(bk + 2, 2 * ns + 1)):
                        if zg[j, k] == _UNSEEN:
                            zg[j, k] = _warped_zncc(buf, norm1, I2, cx + (k - ns) * step,
                                                    cy + (j - ns) * step, jxx, jxy, jyx, jyy, half)
                        if zg[j, k] > zg[nj, nk]:
                            nj = j
                            nk = k
                if nj == bj and nk == bk:
                    break
                bj = nj
                bk = nk
            best = zg[bj, bk]
            ox = 0.0
            oy = 0.0
            interior = 0 < bj < 2 * ns and 0 < bk < 2 * ns
            if interior:
                for j in range(bj - 1, bj + 2):
                    for k in range(bk - 1, bk + 2):
                        if not zg[j, k] > _INVALID:
                            interior = False
            if interior:
                # the same 3x3 least-squares quadratic as refine_quadratic, in grid units
                colm = zg[bj - 1, bk - 1] + zg[bj, bk - 1] + zg[bj + 1, bk - 1]
                col0 = zg[bj - 1, bk] + zg[bj, bk] + zg[bj + 1, bk]
                colp = zg[bj - 1, bk + 1] + zg[bj, bk + 1] + zg[bj + 1, bk + 1]
                rowm = zg[bj - 1, bk - 1] + zg[bj - 1, bk] + zg[bj - 1, bk + 1]
                row0 = zg[bj, bk - 1] + zg[bj, bk] + zg[bj, bk + 1]
                rowp = zg[bj + 1, bk - 1] + zg[bj + 1, bk] + zg[bj + 1, bk + 1]
                b = (colp - colm) / 6.0
                c = (rowp - rowm) / 6.0
                d = (colp + colm - 2.0 * col0) / 6.0
                g = (rowp + rowm - 2.0 * row0) / 6.0
                e = (zg[bj + 1, bk + 1] - zg[bj + 1, bk - 1] - zg[bj - 1, bk + 1] + zg[bj - 1, bk - 1]) / 4.0
                det = 4.0 * d * g - e * e
                if d < 0.0 and det > 0.0:
                    ox = min(1.0, max(-1.0, (-2.0 * g * b + e * c) / det))
                    oy = min(1.0, max(-1.0, (e * b - 2.0 * d * c) / det))
            rx = cx + (bk - ns + ox) * step
            ry = cy + (bj - ns + oy) * step
        if not best > min_zncc:
            continue
        out_x[i] = rx
        out_y[i] = ry
        used[i] = True
    return out_x, out_y, used


def refine_affine(I1, mean1, inv1, I2, x1, y1, x2, y2, half, use_f, F, min_zncc, rows=None):
    """Affine-adapted refinement of the matches (``_AFFINE_PASSES`` passes).

    x1, y1, x2, y2: (M,) int32 integer matches; rows: (R,) int64 the matches whose position is
    wanted, or None for all. A later pass fits each match's affine map on its neighbours'
    positions from the pass before, so pass p (1, 2, ...) runs on the matches within
    ``(_AFFINE_PASSES - p) * _AFFINE_RADIUS`` px (Chebyshev) of a wanted one: the wanted rows come
    out exactly as in a run over all matches, at a fraction of the cost when few are wanted.
    Returns x2, y2 (M,) float64 and used (M,) bool, False where no pass produced a position
    (x2, y2 are then the integer ones, as everywhere outside the wanted rows' neighbourhoods).

    Image 1 is taken in bands of rows (``_BAND_PIXELS``): a match's fit reads only the fields
    within ``_AFFINE_RADIUS`` rows of it, so each band's fields are filtered on the band and that
    margin, and the per-pixel fields of the whole image are never held at once (at 3072 x 2048
    they were 700 MB). The outcome is the whole image's, bit for bit.
    """
    H1, W1 = I1.shape
    cur_x = x2.astype(np.float64)
    cur_y = y2.astype(np.float64)
    used = np.zeros(x1.shape[0], dtype=bool)
    by_row = np.argsort(y1, kind="stable")  # the matches row after row of image 1
    row_start = np.searchsorted(y1[by_row], np.arange(H1 + 1))  # row r's are by_row[row_start[r]:row_start[r + 1]]
    band = max(1, _BAND_PIXELS // max(W1, 1))
    for p in range(_AFFINE_PASSES):
        sel = _within(x1, y1, rows, (_AFFINE_PASSES - 1 - p) * _AFFINE_RADIUS, (H1, W1))
        wanted = np.zeros(x1.shape[0], bool)
        wanted[sel] = True
        # pass 1 fits the integer matches, later passes the positions of the pass before
        new_x, new_y = cur_x.copy(), cur_y.copy()
        for top in range(0, H1, band):
            bottom = min(top + band, H1)
            here = by_row[row_start[top]:row_start[bottom]]
            here = np.sort(here[wanted[here]])
            if not len(here):
                continue
            lo, hi = max(top - _AFFINE_RADIUS, 0), min(bottom + _AFFINE_RADIUS, H1)
            near = by_row[row_start[lo]:row_start[hi]]  # the matches the band's fits read
            matched = np.zeros((hi - lo, W1), bool)
            matched[y1[near] - lo, x1[near]] = True
            xs, ys = x1[here], y1[here]
            system = _fit_system(matched, xs, ys - lo, _AFFINE_RADIUS, _AFFINE_MIN_MATCHES)
            del matched
            fx = np.full((hi - lo, W1), np.nan)
            fy = np.full((hi - lo, W1), np.nan)
            fx[y1[near] - lo, x1[near]] = cur_x[near]
            fy[y1[near] - lo, x1[near]] = cur_y[near]
            aff = _affine_fields(fx, fy, xs, ys, _AFFINE_RADIUS, system, lo)
            del fx, fy, system
            prev_x, prev_y = cur_x[here], cur_y[here]  # the matches are independent: threads share them out
            bx, by, u = concat_chunks(lambda a, b: _refine_affine_pass(
                I1, mean1, inv1, I2, xs[a:b], ys[a:b], aff[a:b], use_f, F, half, _SEARCH_PX, _SEARCH_STEP,
                min_zncc, prev_x[a:b], prev_y[a:b]), len(xs), _MATCHES_PER_THREAD)
            new_x[here], new_y[here] = bx, by
            used[here] |= u
        cur_x, cur_y = new_x, new_y
    return cur_x, cur_y, used


def _within(x1, y1, rows, radius, shape):
    """All matches (a slice) when rows is None, else the rows (K,) int64 of the matches x1, y1
    (M,) lying within ``radius`` px (Chebyshev) of a match in ``rows``, in increasing order."""
    if rows is None:
        return slice(None)
    if radius == 0:
        return np.unique(rows)
    wanted = np.zeros(shape, np.uint8)
    wanted[y1[rows], x1[rows]] = 1
    near = cv2.dilate(wanted, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))
    return np.flatnonzero(near[y1, x1])
