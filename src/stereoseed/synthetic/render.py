"""The synthetic scene's Numba renderer: ray casting against the box and the ground, shading,
box-filtered supersampling; and the sensor's noise (:func:`add_noise`).

World frame and face labels are those of :mod:`stereoseed.synthetic.scene`, which sets the scene up
(cameras, textures, constants) and calls these kernels; every kernel takes the geometry and the
appearance as arguments. Rays are ``o + t d`` with o, d (3,) float64; textures are label-indexed
(n, T, T) float32 arrays of unit-variance noise sampled in texel coordinates.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from stereoseed.features.image import sample_bilinear
from stereoseed.geometry.lens import undistort_pixel_centre, undistort_sample

@njit(cache=True)
def _slab(o, d, lo, hi, lab_rising, lab_falling, tnear, tfar, label):
    """One slab lo <= o + t d <= hi of the slab method: the entry (tnear, label) and exit tfar
    so far, updated, and whether the ray can still meet the box (a ray parallel to the slab
    must start inside it). lab_rising / lab_falling: the face entered when d > 0 / d < 0."""
    if d != 0.0:
        t1 = (lo - o) / d
        t2 = (hi - o) / d
        if d > 0.0:
            enter, leave, lab = t1, t2, lab_rising
        else:
            enter, leave, lab = t2, t1, lab_falling
        if enter > tnear:
            tnear, label = enter, lab
        return tnear, min(tfar, leave), label, True
    return tnear, tfar, label, not (o < lo or o > hi)


@njit(cache=True)
def _intersect(ox, oy, oz, dx, dy, dz, half, height):
    """First hit of the ray o + t d (t > 0) with the box or the ground: (t, label), (inf, -1)."""
    # Slab method; the entering face is the slab whose entry parameter is the largest. Face 0,
    # the bottom, is only reachable from under the ground.
    tnear, tfar, label, in_x = _slab(ox, dx, -half, half, 3, 1, -np.inf, np.inf, -1)
    tnear, tfar, label, in_y = _slab(oy, dy, -half, half, 4, 2, tnear, tfar, label)
    tnear, tfar, label, in_z = _slab(oz, dz, 0.0, height, 0, 5, tnear, tfar, label)
    hit_box = in_x and in_y and in_z
    if hit_box and tnear <= tfar and tnear > 0.0:
        return tnear, label
    # The box stands on the ground, so a ray that misses it can only meet the ground plane.
    if dz < 0.0 and oz > 0.0:
        return -oz / dz, 0
    return np.inf, -1



@njit(cache=True)
def _in_grid(s, n, size, gap):
    """True if local coordinate s falls inside one of n intervals [gap + k(size+gap), +size)."""
    q = s - gap
    if q < 0.0:
        return False
    # floor of the quotient, not Python's //, which adds an fmod to every sample (~10 % of a
    # render); the two differ only within an ulp of a square's edge (rendered bytes unchanged)
    k = int(np.floor(q / (size + gap)))
    return k < n and q - k * (size + gap) < size


@njit(cache=True)
def _shade_sample(ox, oy, oz, dx, dy, dz, half, height, face_o, face_u, face_v, grid, sq_size,
                  sq_gap, tex_faces, face_texel, tex_ground, ground_texel, ground_radius, albedo,
                  shade, tints, sky, far_ground):
    """Linear RGB colour seen along one ray. Returns (r, g, b)."""
    t, label = _intersect(ox, oy, oz, dx, dy, dz, half, height)
    if label < 0:
        return sky[0], sky[1], sky[2]
    x = ox + t * dx
    y = oy + t * dy
    z = oz + t * dz
    if label == 0:
        if x * x + y * y > ground_radius * ground_radius:
            a = far_ground * shade[0]
            return a * tints[2, 0], a * tints[2, 1], a * tints[2, 2]
        zt = sample_bilinear(tex_ground[0], (x + ground_radius) / ground_texel - 0.5,
                            (y + ground_radius) / ground_texel - 0.5)
        row = 2
        tint = 1
    else:
        px = x - face_o[label, 0]
        py = y - face_o[label, 1]
        pz = z - face_o[label, 2]
        s = px * face_u[label, 0] + py * face_u[label, 1] + pz * face_u[label, 2]
        r = px * face_v[label, 0] + py * face_v[label, 1] + pz * face_v[label, 2]
        zt = sample_bilinear(tex_faces[label], s / face_texel - 0.5, r / face_texel - 0.5)
        # Squares are tested analytically, not painted in the texture, so their edges are exact.
        dark = (_in_grid(s, grid[label, 0], sq_size, sq_gap)
                and _in_grid(r, grid[label, 1], sq_size, sq_gap))
        row = 1 if dark else 0
        tint = 0
    a = min(max(albedo[row, 0] + albedo[row, 1] * zt, albedo[row, 2]), albedo[row, 3])
    a *= shade[label]
    return a * tints[tint, 0], a * tints[tint, 1], a * tints[tint, 2]


@njit(cache=True)
def _sample_ray(us, vs, Minv, Kinv, Rt, has_lens, lens, r2_max, centre_ok, xdc, ydc, xc, yc, jxx, jxy, jyy, det):
    """World direction (dx, dy, dz) of the ray through sub-pixel (us, vs), and whether it exists.
    Pinhole: Minv (us, vs, 1). Behind a lens: the (distorted) sub-pixel is undistorted (Newton,
    :mod:`stereoseed.geometry.lens`) before R^T is applied, started from the linearisation at the pixel
    centre (xdc, ydc) -> (xc, yc) with Jacobian (jxx, jxy, jyy) when ``centre_ok``."""
    if not has_lens:
        dx = Minv[0, 0] * us + Minv[0, 1] * vs + Minv[0, 2]
        dy = Minv[1, 0] * us + Minv[1, 1] * vs + Minv[1, 2]
        dz = Minv[2, 0] * us + Minv[2, 1] * vs + Minv[2, 2]
        return dx, dy, dz, True
    xd = Kinv[0, 0] * us + Kinv[0, 1] * vs + Kinv[0, 2]
    yd = Kinv[1, 0] * us + Kinv[1, 1] * vs + Kinv[1, 2]
    x, y, ok = undistort_sample(xd, yd, xdc, ydc, xc, yc, jxx, jxy, jyy, det, centre_ok, lens, r2_max)
    dx = Rt[0, 0] * x + Rt[0, 1] * y + Rt[0, 2]
    dy = Rt[1, 0] * x + Rt[1, 1] * y + Rt[1, 2]
    dz = Rt[2, 0] * x + Rt[2, 1] * y + Rt[2, 2]
    return dx, dy, dz, ok


@njit(parallel=True, cache=True)
def render_kernel(Minv, Kinv, Rt, has_lens, lens, r2_max, C, height_px, width_px, ss, half, height, face_o,
                   face_u, face_v, grid, sq_size, sq_gap, tex_faces, face_texel, tex_ground, ground_texel,
                   ground_radius, albedo, shade, tints, sky, far_ground):
    """Box-filtered supersampled render -> (H, W, 3) linear RGB. Minv = R^T K^-1 (3, 3), C (3,).
    Behind a lens (``has_lens``; Kinv = K^-1, Rt = R^T, lens (5,) = (k1, k2, p1, p2, k3), r2_max
    from :func:`stereoseed.geometry.lens.principal_r2`) each sub-sample's pixel is undistorted before its
    ray is cast, so the image is the pinhole image distorted; a sample without a principal-branch
    ray shows the sky. The pixel centre is undistorted first; its sub-samples start from its
    linearisation, which leaves one Newton step to each."""
    out = np.empty((height_px, width_px, 3), dtype=np.float64)
    inv = 1.0 / (ss * ss)
    for v in prange(height_px):
        for u in range(width_px):
            xdc = ydc = xc = yc = jxx = jxy = jyy = det = 0.0
            centre_ok = False
            if has_lens:
                xdc = Kinv[0, 0] * u + Kinv[0, 1] * v + Kinv[0, 2]
                ydc = Kinv[1, 0] * u + Kinv[1, 1] * v + Kinv[1, 2]
                xc, yc, jxx, jxy, jyy, det, centre_ok = undistort_pixel_centre(xdc, ydc, lens, r2_max)
            acc_r = 0.0
            acc_g = 0.0
            acc_b = 0.0
            for j in range(ss):
                vs = v + (j + 0.5) / ss - 0.5
                for i in range(ss):
                    us = u + (i + 0.5) / ss - 0.5
                    dx, dy, dz, ok = _sample_ray(us, vs, Minv, Kinv, Rt, has_lens, lens, r2_max, centre_ok,
                                                 xdc, ydc, xc, yc, jxx, jxy, jyy, det)
                    if not ok:
                        acc_r += sky[0]
                        acc_g += sky[1]
                        acc_b += sky[2]
                        continue
                    r, g, b = _shade_sample(C[0], C[1], C[2], dx, dy, dz, half, height, face_o,
                                            face_u, face_v, grid, sq_size, sq_gap, tex_faces,
                                            face_texel, tex_ground, ground_texel, ground_radius,
                                            albedo, shade, tints, sky, far_ground)
                    acc_r += r
                    acc_g += g
                    acc_b += b
            out[v, u, 0] = acc_r * inv
            out[v, u, 1] = acc_g * inv
            out[v, u, 2] = acc_b * inv
    return out


@njit(parallel=True, cache=True)
def cast_kernel(C, dirs, half, height):
    """First hits of rays C + t dirs[n]: t (N,) float64 (inf if none), labels (N,) int8."""
    n = dirs.shape[0]
    ts = np.empty(n, dtype=np.float64)
    labels = np.empty(n, dtype=np.int8)
    for k in prange(n):
        t, lab = _intersect(C[0], C[1], C[2], dirs[k, 0], dirs[k, 1], dirs[k, 2], half, height)
        ts[k] = t
        labels[k] = lab
    return ts, labels


def add_noise(image: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Add Gaussian grey-level noise to a uint8 image, round and clip. -> uint8, same shape.

    image: (H, W) or (H, W, 3) uint8; sigma in grey levels (0..255). For colour images one sample
    per pixel is added to all channels: the grey conversion (weights summing to 1) then carries
    noise of standard deviation sigma, which is what the paper's Fig. 9 varies.
    """
    image = np.asarray(image)
    if sigma <= 0:
        return image.copy()
    noise = rng.normal(0.0, sigma, size=image.shape[:2])
    if image.ndim == 3:
        noise = noise[:, :, None]
    return np.clip(np.rint(image.astype(np.float64) + noise), 0, 255).astype(np.uint8)
