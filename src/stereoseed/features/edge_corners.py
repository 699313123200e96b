"""Junctions moved to the intersection of their two edges (sub-pixel corner localisation).

Where the cornerSubPix junction model holds (:func:`stereoseed.features.harris._refine_subpixel`), the
two edge directions come from the gradients in a (2 * _EDGE_WINDOW + 1)^2 window (the apex
excluded); each edge is located by sub-pixel intensity profiles across it _EDGE_FROM..._EDGE_TO
px from the corner, a straight line is fitted to those edge points and the two lines are
intersected. Away from the apex an edge is a clean step, so its line does not carry
cornerSubPix's bias at a blurred L corner (figures in ``docs/features.md``).

Images: gray (H, W) float32 in [0, 1] with its Sobel gradients gx, gy (H, W) float32; points
(N, 2) float64 ``(x, y)`` pixels, (0, 0) the centre of the top-left pixel.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from stereoseed.features.image import sample_bilinear

_EDGE_WINDOW = 6
_EDGE_APEX = 1.5  # px around the corner whose gradients mix both edges
_EDGE_FROM, _EDGE_TO, _EDGE_STEP = 2.0, 10.0, 0.5  # profile positions along an edge (px)
_EDGE_PROFILE_HALF = 2.5  # half-length of a profile across the edge (px), sampled every 0.25 px
_EDGE_MIN_ANGLE_DEG = 25.0  # the two edges must differ by this much to intersect well
_EDGE_MAX_SCATTER = 0.3  # px rms of the edge points about their line: a straight edge
_EDGE_MAX_SHIFT = 1.0  # px from the junction's position: farther is another structure


@njit(cache=True, nogil=True)
def _edge_line(gray, cx, cy, nx, ny, sides, half, s_from, s_to, s_step, max_scatter):
    """Sub-pixel edge points along the edge of normal (nx, ny) leaving (cx, cy) on ``sides``
    (+1, -1 or both: 0) and their total-least-squares line. Returns (ok, nx, ny, c): n.p = c."""
    h, w = gray.shape
    dx, dy = -ny, nx
    n_t = int(round(2 * half / 0.25)) + 1
    vals = np.empty(n_t)
    px = np.empty(64)
    py = np.empty(64)
    count = 0
    for side in (1.0, -1.0):
        if sides != 0 and side != sides:
            continue
        s = s_from
        while s <= s_to + 1e-9 and count < 64:
            bx = cx + side * s * dx
            by = cy + side * s * dy
            inside = True
            for k in range(n_t):
                t = -half + 0.25 * k
                x = bx + t * nx
                y = by + t * ny
                if x < 0.0 or y < 0.0 or x >= w - 1.0 or y >= h - 1.0:
                    inside = False
                    break
                vals[k] = sample_bilinear(gray, x, y)
            s += s_step
            if not inside:
                continue
            best, k0 = 0.0, 0
            for k in range(n_t - 1):
                d = abs(vals[k + 1] - vals[k])
                if d > best:
                    best, k0 = d, k
            if best <= 0.0:  # a flat profile
                continue
            # centroid of the derivative's main lobe (within 1.25 px of its peak); a step holds
            # most of the profile's variation there, blurred or not (texture or a second edge
            # spreads it)
            num, den, total = 0.0, 0.0, 0.0
            t0 = -half + 0.25 * (k0 + 0.5)
            for k in range(n_t - 1):
                t = -half + 0.25 * (k + 0.5)
                d = abs(vals[k + 1] - vals[k])
                total += d
                if abs(t - t0) <= 1.25:
                    num += d * t
                    den += d
            if den < 0.6 * total:
                continue
            off = num / den
            px[count] = bx + off * nx
            py[count] = by + off * ny
            count += 1
    if count < 5:
        return False, 0.0, 0.0, 0.0
    mx = px[:count].mean()
    my = py[:count].mean()
    sxx, sxy, syy = 0.0, 0.0, 0.0
    for i in range(count):
        ex, ey = px[i] - mx, py[i] - my
        sxx += ex * ex
        sxy += ex * ey
        syy += ey * ey
    sxx /= count
    sxy /= count
    syy /= count
    # smallest eigenvalue and its eigenvector: the line's normal
    tr = sxx + syy
    disc = np.sqrt(max((sxx - syy) ** 2 / 4.0 + sxy * sxy, 0.0))
    lam_min = tr / 2.0 - disc
    if np.sqrt(max(lam_min, 0.0)) > max_scatter:
        return False, 0.0, 0.0, 0.0
    if abs(sxy) > 1e-12:
        ex, ey = lam_min - syy, sxy
    elif sxx < syy:
        ex, ey = 1.0, 0.0
    else:
        ex, ey = 0.0, 1.0
    norm = np.sqrt(ex * ex + ey * ey)
    ex /= norm
    ey /= norm
    return True, ex, ey, ex * mx + ey * my


@njit(cache=True, nogil=True)
def _edge_corner_kernel(gray, gx, gy, pts, radius, apex, half, s_from, s_to, s_step, min_angle_deg,
                        max_scatter, max_shift, out, ok):
    h, w = gray.shape
    size = (2 * radius + 1) ** 2
    xs = np.empty(size)
    ys = np.empty(size)
    ms = np.empty(size)
    c2 = np.empty(size)
    s2 = np.empty(size)
    in_a = np.empty(size, np.bool_)  # which of the two edge orientations a gradient belongs to
    cos_sep = np.cos(np.radians(2.0 * min_angle_deg))
    for i in range(pts.shape[0]):
        cx, cy = pts[i, 0], pts[i, 1]
        ix, iy = int(round(cx)), int(round(cy))
        ok[i] = False
        if ix - radius < 1 or iy - radius < 1 or ix + radius >= w - 1 or iy + radius >= h - 1:
            continue
        mmax = 0.0
        for y in range(iy - radius, iy + radius + 1):
            for x in range(ix - radius, ix + radius + 1):
                m = np.hypot(gx[y, x], gy[y, x])
                if m > mmax:
                    mmax = m
        if mmax <= 0.0:
            continue
        n = 0
        for y in range(iy - radius, iy + radius + 1):
            for x in range(ix - radius, ix + radius + 1):
                gxv, gyv = gx[y, x], gy[y, x]
                m = np.hypot(gxv, gyv)
                if m >= 0.5 * mmax and np.hypot(x - cx, y - cy) >= apex:
                    xs[n], ys[n], ms[n] = x, y, m
                    c2[n] = (gxv * gxv - gyv * gyv) / (m * m)  # doubled gradient angle
                    s2[n] = 2.0 * gxv * gyv / (m * m)
                    n += 1
        if n < 8:
            continue
        # two edge orientations: 2-means on the doubled angles, from the strongest gradient and
        # the one least like it
        a = int(np.argmax(ms[:n]))
        ax, ay = c2[a], s2[a]
        b, worst = 0, 2.0
        for j in range(n):
            d = ax * c2[j] + ay * s2[j]
            if d < worst:
                b, worst = j, d
        bx, by = c2[b], s2[b]
        good = True
        for _ in range(6):
            sax, say, sbx, sby = 0.0, 0.0, 0.0, 0.0
            na, nb = 0, 0
            for j in range(n):
                if ax * c2[j] + ay * s2[j] >= bx * c2[j] + by * s2[j]:
                    sax += ms[j] * c2[j]
                    say += ms[j] * s2[j]
                    na += 1
                else:
                    sbx += ms[j] * c2[j]
                    sby += ms[j] * s2[j]
                    nb += 1
            if na < 4 or nb < 4:
                good = False
                break
            la, lb = np.hypot(sax, say), np.hypot(sbx, sby)
            if la == 0.0 or lb == 0.0:
                good = False
                break
            ax, ay, bx, by = sax / la, say / la, sbx / lb, sby / lb
        if not good or ax * bx + ay * by > cos_sep:
            continue
        for j in range(n):
            in_a[j] = ax * c2[j] + ay * s2[j] >= bx * c2[j] + by * s2[j]
        normals = np.empty((2, 2))
        sides = np.zeros(2, np.int64)
        for e in range(2):
            vx, vy = (ax, ay) if e == 0 else (bx, by)
            th = 0.5 * np.arctan2(vy, vx)
            normals[e, 0], normals[e, 1] = np.cos(th), np.sin(th)
            # which way the edge leaves the corner (an L corner: one side; an X junction: both)
            side, total = 0.0, 0.0
            for j in range(n):
                if in_a[j] == (e == 0):
                    along = (xs[j] - cx) * (-normals[e, 1]) + (ys[j] - cy) * normals[e, 0]
                    side += ms[j] * along
                    total += ms[j] * abs(along)
            sides[e] = 0 if abs(side) < 0.5 * total else (1 if side > 0 else -1)
        # Where the edges leaving the corner make an acute angle, a profile across one of them
        # s px out meets the other at t = s tan(angle): start where the profile's lobe stays
        # clear of it (an obtuse L corner has no such crossing; an X junction always has one).
        cos_rays = normals[0, 1] * normals[1, 1] + normals[0, 0] * normals[1, 0]  # = d0 . d1
        if sides[0] != 0 and sides[1] != 0:
            cos_rays *= sides[0] * sides[1]
        else:
            cos_rays = abs(cos_rays)
        start = s_from
        if cos_rays > 0.0:
            start = max(s_from, (half + 1.25) * cos_rays / np.sqrt(max(1.0 - cos_rays * cos_rays, 1e-12)))
        if s_to - start < 2.0:
            continue
        lines = np.empty((2, 3))
        for e in range(2):
            fit, lx, ly, lc = _edge_line(gray, cx, cy, normals[e, 0], normals[e, 1], sides[e], half, start, s_to,
                                         s_step, max_scatter)
            if not fit:
                good = False
                break
            lines[e, 0], lines[e, 1], lines[e, 2] = lx, ly, lc
        if not good:
            continue
        det = lines[0, 0] * lines[1, 1] - lines[0, 1] * lines[1, 0]
        if abs(det) < 1e-6:
            continue
        qx = (lines[0, 2] * lines[1, 1] - lines[0, 1] * lines[1, 2]) / det
        qy = (lines[0, 0] * lines[1, 2] - lines[0, 2] * lines[1, 0]) / det
        if np.hypot(qx - cx, qy - cy) > max_shift:
            continue
        out[i, 0], out[i, 1] = qx, qy
        ok[i] = True


def corners_on_edges(gray: np.ndarray, gx: np.ndarray, gy: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Junctions (N, 2) moved to the intersection of their two edges where both edges are found
    and straight (see _EDGE_WINDOW). Returns (positions (N, 2), moved (N,) bool)."""
    out = np.array(points, np.float64, copy=True)
    ok = np.zeros(len(out), np.bool_)
    if len(out):
        _edge_corner_kernel(np.ascontiguousarray(gray, np.float32), gx, gy, out.copy(), _EDGE_WINDOW, _EDGE_APEX,
                            _EDGE_PROFILE_HALF, _EDGE_FROM, _EDGE_TO, _EDGE_STEP, _EDGE_MIN_ANGLE_DEG,
                            _EDGE_MAX_SCATTER, _EDGE_MAX_SHIFT, out, ok)
    return out, ok
