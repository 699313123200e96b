"""The Strecha sets' conversion for :mod:`stereoseed.io.sample_data`: the published images and
per-image ``.camera`` files become the layout ../shared/data holds (its SOURCE.txt): the
images reduced 4x by block averaging (768x512 JPEGs, quality 95), a Middlebury par file of
their cameras, and, for the fountain, the published images in ``full/`` with a par file of their
own. Checked on the fountain: from the published images and cameras this writes the reduced
JPEGs and both par files of ../shared/data byte for byte."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stereoseed.errors import StereoseedError

__all__ = ["convert_strecha", "read_strecha_camera", "middlebury_par_text", "REDUCTION"]

# the stored copies' par files print 12 significant digits at the published size, 10 reduced:
# written alike, the files are the stored ones byte for byte
FULL_DIGITS, REDUCED_DIGITS = 12, 10
# the reduction the stored copies were made with: 3072x2048 -> 768x512, the size the pipeline's
# tests and benchmarks run at (the published size is kept in full/ where the copy has it)
REDUCTION = 4
JPEG_QUALITY = 95  # the stored copies' quality: the reduced images are written as they were
CAMERA_NUMBERS = 26  # K (9), radial distortion (3), camera-to-world R (9), centre (3), width and height


def read_strecha_camera(path: Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """A Strecha ``.camera`` file (K row by row, three distortion terms, the camera-to-world
    rotation row by row, the centre, the image's width and height) as (K, P = K [R^T | -R^T C]
    of the published pixels, (width, height)). Refused: other than 26 numbers, a non-zero
    distortion (the published images are undistorted; a lens here is not modelled)."""
    try:
        values = [float(v) for v in path.read_text(encoding="ascii").split()]
    except (UnicodeDecodeError, ValueError) as e:
        raise StereoseedError(f"{path.name}: not a Strecha .camera file ({e})") from None
    if len(values) != CAMERA_NUMBERS:
        raise StereoseedError(f"{path.name}: {len(values)} numbers, a Strecha .camera file has {CAMERA_NUMBERS}")
    K = np.array(values[0:9]).reshape(3, 3)
    if any(values[9:12]):
        raise StereoseedError(f"{path.name}: non-zero lens distortion {values[9:12]}; the conversion expects the "
                              "published undistorted images")
    R_cw = np.array(values[12:21]).reshape(3, 3)
    C = np.array(values[21:24])
    R = R_cw.T
    return K, K @ np.hstack([R, (-R @ C)[:, None]]), (int(values[24]), int(values[25]))


def reduced_K(K: np.ndarray, factor: int = REDUCTION) -> np.ndarray:
    """K of the image reduced ``factor`` times by block averaging: pixel (0, 0) is the centre
    of the top-left pixel in both, so x' = (x + 0.5) / factor - 0.5."""
    S = np.array([[1 / factor, 0, 0.5 / factor - 0.5], [0, 1 / factor, 0.5 / factor - 0.5], [0, 0, 1]])
    return S @ K


def middlebury_par_text(cameras: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], digits: int = 12) -> str:
    """Middlebury's par format: the count, then per image its name, K, R and t row by row
    (``digits`` significant digits: the published cameras have 6)."""
    lines = [str(len(cameras))]
    for name, (K, R, t) in cameras.items():
        lines.append(" ".join([name] + [f"{v:.{digits}g}" for v in (*K.ravel(), *R.ravel(), *t.ravel())]))
    return "\n".join(lines) + "\n"


def convert_strecha(set_name: str, staging: Path, camera_files: dict[str, Path], keep_full: bool) -> None:
    """``staging/full/NAME.jpg`` (the published images) and their ``.camera`` files (by image
    name) -> the reduced images, ``SET_par.txt`` and ``ring_order.txt`` in ``staging`` (the
    walk is the published numbering); with ``keep_full``, ``full/`` keeps the published images
    with ``SET_full_par.txt`` and a ring_order.txt, else it is removed."""
    import cv2

    full = staging / "full"
    names = sorted(camera_files)
    full_cams, small_cams = {}, {}
    for name in names:
        K, P, (w, h) = read_strecha_camera(camera_files[name])
        image = cv2.imread(str(full / name), cv2.IMREAD_COLOR)
        if image is None or image.shape[:2] != (h, w):
            got = "unreadable" if image is None else f"{image.shape[1]}x{image.shape[0]}"
            raise StereoseedError(f"{set_name}: {name} is {got}, its camera file says {w}x{h}; report it")
        if w % REDUCTION or h % REDUCTION:
            raise StereoseedError(f"{set_name}: {name} is {w}x{h}, not a multiple of {REDUCTION}")
        Rt = np.linalg.solve(K, P)
        full_cams[name] = (K, Rt[:, :3], Rt[:, 3])
        small_cams[name] = (reduced_K(K), Rt[:, :3], Rt[:, 3])
        small = cv2.resize(image, (w // REDUCTION, h // REDUCTION), interpolation=cv2.INTER_AREA)  # block mean
        ok, data = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise StereoseedError(f"{set_name}: {name}: OpenCV could not encode the reduced image")
        (staging / name).write_bytes(data.tobytes())
    order = "".join(f"{n}\n" for n in names)
    (staging / f"{set_name}_par.txt").write_text(middlebury_par_text(small_cams, REDUCED_DIGITS), encoding="utf-8")
    (staging / "ring_order.txt").write_text(order, encoding="utf-8")
    if keep_full:
        (full / f"{set_name}_full_par.txt").write_text(middlebury_par_text(full_cams, FULL_DIGITS), encoding="utf-8")
        (full / "ring_order.txt").write_text(order, encoding="utf-8")
    else:
        for name in names:
            (full / name).unlink()
        full.rmdir()
