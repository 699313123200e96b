"""Small random cameras and point clouds for the geometry tests (no rendering needed)."""
import cv2
import numpy as np

from stereoseed.geometry.projection import compose_projection, decompose_projection


def look_at_camera(center, target=(0.0, 0.0, 0.2), f=800.0, skew=0.0, aspect=1.0, pp=(320.0, 240.0)):
    """K, R, t, P of a camera at ``center`` looking at ``target``, image y down = world -z."""
    center = np.asarray(center, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    t = -R @ center
    K = np.array([[f, skew, pp[0]], [0.0, f * aspect, pp[1]], [0.0, 0.0, 1.0]])
    return K, R, t, compose_projection(K, R, t)


def ring_camera(angle_deg, distance=1.4, height=0.8, **kw):
    a = np.radians(angle_deg)
    return look_at_camera((distance * np.cos(a), distance * np.sin(a), height), **kw)


def box_points(rng, n, half=0.17, height=0.44):
    """n points on the visible surfaces of a box (non-coplanar by construction)."""
    pts = rng.uniform([-half, -half, 0.0], [half, half, height], size=(n, 3))
    face = rng.integers(0, 3, n)
    pts[face == 0, 0] = half
    pts[face == 1, 1] = half
    pts[face == 2, 2] = height
    return pts


def band_noise(shape: tuple[int, int], seed: int = 0) -> np.ndarray:
    """Smooth random texture in [0, 1], blobs of a few pixels: (H, W) float32."""
    rng = np.random.default_rng(seed)
    img = np.zeros(shape, np.float32)
    for sigma, weight in ((1.2, 1.0), (2.5, 0.8), (5.0, 0.6)):
        layer = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
        img += weight * layer / layer.std()
    return (img - img.min()) / (img.max() - img.min())


def relative_pose(P_left, P_right):
    """(R_rl, t_rl) of the right camera in the left one's frame, by decomposing both: the
    reference Rig.from_projections is tested against."""
    _, R_l, t_l = decompose_projection(P_left)
    _, R_r, t_r = decompose_projection(P_right)
    R_rl = R_r @ R_l.T
    return R_rl, t_r - R_rl @ t_l


def make_rig(baseline=0.12, toe_in_deg=5.0, focal_ratio=1.03):
    """The renderer's rig (640 x 480, 800 px) with these settings."""
    from stereoseed.synthetic.rig import RigConfig, rig_of

    return rig_of(RigConfig(baseline=baseline, toe_in_deg=toe_in_deg, focal_ratio=focal_ratio))


def opencv_undistort_points(pixels, K, distortion, P, criteria, R=None):
    """OpenCV's iterative undistortion as the oracle, (N, 2): cv2.undistortPoints takes the
    iterations' criteria in OpenCV 5, cv2.undistortPointsIter in 4.x (nerfstudio's 4.10)."""
    import cv2

    src = np.asarray(pixels, np.float64).reshape(-1, 1, 2)
    d = np.asarray(distortion, np.float64)
    if hasattr(cv2, "undistortPointsIter"):
        return cv2.undistortPointsIter(src, K, d, R, P, criteria).reshape(-1, 2)
    return cv2.undistortPoints(src, K, d, None, R, P, criteria).reshape(-1, 2)
