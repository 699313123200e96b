"""Image primitives shared by the stages: grey conversion and bilinear sampling.

Conventions: images are (H, W) arrays indexed ``img[y, x]``; pixel (0, 0) is the centre of the
top-left pixel (see :mod:`stereoseed.geometry.projection`). Colour images are in OpenCV's BGR(A) order.
"""
from __future__ import annotations

import cv2
import numpy as np
from numba import njit

from stereoseed.errors import StereoseedError

__all__ = ["to_gray", "sample_bilinear"]

# ITU-R BT.601 luma weights in B, G, R order: the ones cv2.COLOR_BGR2GRAY uses.
_BGR_WEIGHTS = np.array([0.114, 0.587, 0.299])


def to_gray(image: np.ndarray, dtype: type = np.float32) -> np.ndarray:
    """Grey levels in [0, 1]: Y = 0.299 R + 0.587 G + 0.114 B of the intensities scaled to [0, 1].

    image: (H, W) or (H, W, 1) grey, (H, W, 3) BGR or (H, W, 4) BGRA (alpha ignored).
    Scaling: uint8 is divided by 255, uint16 by 65535; bool and float images are taken to be in
    [0, 1], except a float image whose maximum exceeds 1, taken to be in [0, 255]. NaN/inf become
    0 and the result is clipped to [0, 1].
    dtype: np.float32 (default; the sparse stage) or np.float64 (the propagation, whose 25-term
    ZNCC sums need the precision on windows barely above the texture threshold). Both compute the
    same values: the channels are scaled first, then weighted (float32 by cv2.cvtColor, float64
    by a product with the same weights, since cvtColor has no float64 path).
    Returns (H, W) C-contiguous ``dtype``. Raises StereoseedError for any other shape or dtype.
    """
    dtype = np.dtype(dtype)
    if dtype not in (np.float32, np.float64):
        raise StereoseedError(f"to_gray returns float32 or float64, not {dtype}")
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)):
        raise StereoseedError(
            f"image of shape {img.shape} is not a grey (H, W), BGR (H, W, 3) or BGRA (H, W, 4) "
            "image"
        )
    if img.dtype == np.uint8:
        gray = img.astype(dtype) / dtype.type(255.0)
    elif img.dtype == np.uint16:
        gray = img.astype(dtype) / dtype.type(65535.0)
    elif img.dtype == bool or np.issubdtype(img.dtype, np.number):
        gray = np.nan_to_num(img.astype(dtype), nan=0.0, posinf=0.0, neginf=0.0)
        if gray.size and gray.max() > 1.0:
            gray /= dtype.type(255.0)
    else:
        raise StereoseedError(f"image dtype {img.dtype} is not numeric")
    if gray.ndim == 3:
        if gray.size == 0:
            gray = gray[:, :, 0]
        elif dtype == np.float32:
            code = cv2.COLOR_BGR2GRAY if gray.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
            gray = cv2.cvtColor(np.ascontiguousarray(gray), code)
        else:
            gray = gray[:, :, :3] @ _BGR_WEIGHTS
    return np.ascontiguousarray(np.clip(gray, 0.0, 1.0), dtype=dtype)


# fastmath set: left unset, Numba gives a function the fastmath of the caller that compiles it
# first (the patch alignment's is on), and every kernel calling it would depend on that order
@njit(cache=True, nogil=True, fastmath=False)
def sample_bilinear(img: np.ndarray, x: float, y: float) -> float:
    """Bilinear sample of img (H, W) at (x, y), edges replicated (pixel centres at integers).

    The one bilinear interpolation of the project's Numba code: called from another njit
    function it is inlined, so callers pay no call overhead.
    """
    h, w = img.shape
    x = min(max(x, 0.0), w - 1.0)
    y = min(max(y, 0.0), h - 1.0)
    x0 = min(int(x), w - 2) if w > 1 else 0
    y0 = min(int(y), h - 2) if h > 1 else 0
    fx, fy = x - x0, y - y0
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    top = img[y0, x0] * (1.0 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1.0 - fx) + img[y1, x1] * fx
    return top * (1.0 - fy) + bottom * fy
