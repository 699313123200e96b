"""Hand-offs to the trainers of Gaussian splatting and NeRF: COLMAP's undistorted workspace
(``images/`` and ``sparse/0``, PINHOLE cameras, as ``colmap image_undistorter`` leaves it) and
nerfstudio's ``transforms.json`` (with ``images/`` and the sparse cloud as ``ply_file_path``).

**Undistortion.** A run with a lens worked on undistorted images: the photo's pixel of the
image pixel p that P = K_P [R | t] explains is K_L distort(K_L^-1 p), K_L being the lens's matrix
(``distortion_K`` in cameras.json; K_P itself where a result lacks it). The hand-off writes each
photo again as the image of a PINHOLE camera K [R | t]: the same R and t, K_P's focal lengths,
no skew, and the frame chosen as COLMAP's image_undistorter does by default (``blank_pixels``
0): the largest rectangle whose every pixel comes from inside the photo, centred on that
region, so no black border remains. A barrel lens gives a larger image than the photo, a
pincushion one a smaller; the size stays within ``HandoffConfig.min_scale`` and ``max_scale`` of
the photo's. Pixel q of the new image samples the photo (bilinear) at K_L distort(K_L^-1 K_P
K^-1 q) and the observations move by q = K K_P^-1 p: the same ray, so the model's reprojection
errors are unchanged (a skewed K_P loses its skew exactly, by the resampling). Images of one
camera of the calibration and held intrinsics share one PINHOLE camera.

A result without a lens keeps its photos as they are (copied byte for byte) and K_P as a
PINHOLE camera (its skew dropped, with a warning when that moves a pixel by more than 0.1 px,
as :func:`stereoseed.output.export.colmap_camera` does).

**Flagged cameras.** A trainer fits every image it is given, so a camera the run could not
vouch for (``reliable`` false) is left out, with a warning, unless the run kept its observations
(``reconstruct --keep-flagged``): then it is handed off with the COLMAP export's warning.

The photos are found through the result's record of its inputs (``inputs.json``,
:mod:`stereoseed.output.inputs`: each checked to be the file the run read) or, when
``image_sources`` are given (``--images``: they override the record) or the result has no record,
by name in those folders or lists and in the result's ``keyframes/`` (a rig's renamed images by
their recorded original name and content). Each file is written atomically; the export's
manifest lists them before they are written, so an interrupted export leaves a folder the next
one accepts.
"""
from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from stereoseed.errors import StereoseedError
from stereoseed.geometry.camera import Camera
from stereoseed.geometry.lens import distort_pixels, undistort_pixels
from stereoseed.geometry.models import quaternion_from_rotation
from stereoseed.geometry.projection import to_homogeneous
from stereoseed.io.files import (
    IMAGE_EXTENSIONS,
    VIDEO_EXTENSIONS,
    atomic_path,
    list_images,
    read_image,
    write_image,
    write_json,
)
from stereoseed.io.ply import write_ply
from stereoseed.io.sequence import header_size
from stereoseed.output.export import (
    colmap_files,
    point_ids,
    check_names,
    claim_folder,
    flagged_images,
    flagged_warnings,
    logged,
    skew_warning,
    other_colmap_model,
    record_written,
    remove_written,
    tracks_by_point,
    write_colmap_binary,
    write_colmap_text,
)
from stereoseed.output.inputs import recorded_photos, renamed_photos
from stereoseed.output.reader import Result
from stereoseed.validation import positive

__all__ = ["HandoffConfig", "PinholeImage", "Handoff", "pinhole_images", "undistorted_frame", "undistortion_maps_to",
           "handed_off", "write_colmap_undistorted", "write_nerfstudio", "NERFSTUDIO_PLY"]

log = logging.getLogger(__name__)

NERFSTUDIO_PLY = "sparse_pc.ply"  # the name nerfstudio's own COLMAP conversion gives the cloud
_INSIDE_PX = 1e-6  # a sample this close outside the photo's outermost pixel centre reads that pixel
_SHRINK_STEPS = 64  # at most this many 2-pixel trims of a frame a tangential lens bends off its centred rectangle


@dataclass(frozen=True)
class HandoffConfig:
    # Intrinsics (fx, fy, cx, cy, skew of K_P and of the lens's K, px) this close are one camera:
    # decomposing the P of held intrinsics leaves ~1e-13 px of noise, a zoom moves them by pixels.
    same_intrinsics_px: float = 1e-6
    # The undistorted frame's width and height stay within these fractions of the photo's
    # (COLMAP's image_undistorter defaults): a lens leaving less of the frame free of blank
    # pixels is written at min_scale with black borders (and said so); beyond max_scale a
    # barrel lens's far corners are cut.
    min_scale: float = 0.2
    max_scale: float = 2.0

    def __post_init__(self) -> None:
        positive(self, "same_intrinsics_px", "min_scale", "max_scale")
        if not self.min_scale <= 1.0 <= self.max_scale:
            raise ValueError(f"HandoffConfig: min_scale {self.min_scale!r} <= 1 <= max_scale {self.max_scale!r} "
                             f"is needed (the photo's own frame must be allowed)")


@dataclass(frozen=True)
class PinholeImage:
    """An image as handed off: ``index`` in the result, its PINHOLE camera ``K`` (3, 3) (our pixel
    convention: (0, 0) is the top-left pixel's centre) for an image of ``size`` (width, height),
    ``camera`` (0-based, one per distinct intrinsics), ``to_pinhole`` (3, 3): the run's pixels to
    the new image's (K K_P^-1, the identity when the photo is kept), and ``lens``: (K_P, K_L,
    distortion (5,)) to resample the photo with, None when it is kept as it is."""

    index: int
    K: np.ndarray
    size: tuple[int, int]
    camera: int
    to_pinhole: np.ndarray
    lens: tuple[np.ndarray, np.ndarray, np.ndarray] | None


@dataclass
class Handoff:
    """What a hand-off wrote: images, distinct cameras, points, whether the photos were
    undistorted, the files (paths), the warnings (also logged)."""

    images: int
    cameras: int
    points: int
    undistorted: bool
    written: list[Path]
    warnings: list[str]


def handed_off(result: Result) -> tuple[list[int], list[str]]:
    """(The registered images a trainer gets, in order; the warnings): a flagged camera is
    left out unless the run kept its observations."""
    observed = np.zeros(len(result.names), bool)
    observed[result.tracks["obs_image"]] = True
    flagged = flagged_images(result)
    left_out = [i for i in flagged if not observed[i]]
    warnings = [f"{result.names[i]}: flagged by the run ({result.flags[i]}); left out of the hand-off (a trainer "
                f"fits every image it gets; reconstruct --keep-flagged keeps such a camera's observations and "
                f"hands it off)" for i in left_out]
    kept = [i for i in result.registered if i not in left_out]
    kept_flagged = [w for i, w in zip(flagged, flagged_warnings(result)) if i in kept]
    return kept, warnings + kept_flagged


def _no_skew(K: np.ndarray) -> np.ndarray:
    return np.array([[K[0, 0], 0.0, K[0, 2]], [0.0, K[1, 1], K[1, 2]], [0.0, 0.0, 1.0]])


def _to_rays(pixels: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) -> homogeneous rays (N, 3) through K^-1."""
    return to_homogeneous(pixels) @ np.linalg.inv(K).T


def _source_pixels(q: np.ndarray, K: np.ndarray, K_P: np.ndarray, K_L: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Where pixels q (N, 2) of the PINHOLE image K sample the photo: K_L distort(K_L^-1 K_P K^-1 q)."""
    p = _to_rays(q, K) @ K_P.T
    return distort_pixels(p[:, :2] / p[:, 2:], K_L, d)


def undistorted_frame(K_P: np.ndarray, K_L: np.ndarray, d: np.ndarray, size: tuple[int, int],
                      cfg: HandoffConfig = HandoffConfig(), name: str = "") -> tuple[np.ndarray, tuple[int, int], str | None]:
    """The PINHOLE camera (K (3, 3), (width, height), note or None) of the photo of ``size``
    taken through lens ``d`` on K_L, for the run's camera K_P: K_P's focal lengths, the frame the
    largest rectangle of pixels that all sample inside the photo, centred on that region (the
    note says when min_scale forces black borders)."""
    w, h = size
    K0 = _no_skew(K_P)
    xs, ys = np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)
    edges = [np.column_stack([np.zeros(h), ys]), np.column_stack([np.full(h, w - 1.0), ys]),
             np.column_stack([xs, np.zeros(w)]), np.column_stack([xs, np.full(w, h - 1.0)])]
    back = []
    for e in edges:  # the photo's outermost pixel centres, in K0's frame
        r = _to_rays(undistort_pixels(e, K_L, d), K_P) @ K0.T
        back.append(r[:, :2] / r[:, 2:])
    with np.errstate(all="ignore"):
        lo_x, hi_x = np.nanmax(back[0][:, 0]), np.nanmin(back[1][:, 0])
        lo_y, hi_y = np.nanmax(back[2][:, 1]), np.nanmin(back[3][:, 1])
    if not (np.isfinite([lo_x, hi_x, lo_y, hi_y]).all() and hi_x > lo_x and hi_y > lo_y):
        raise StereoseedError(f"{name}: the lens in cameras.json cannot be inverted at the photo's border; check the "
                              f"calibration's distortion")
    least = (int(np.ceil(cfg.min_scale * w)), int(np.ceil(cfg.min_scale * h)))
    W = int(np.clip(np.floor(hi_x - lo_x) + 1, least[0], np.floor(cfg.max_scale * w)))
    H = int(np.clip(np.floor(hi_y - lo_y) + 1, least[1], np.floor(cfg.max_scale * h)))
    for _ in range(_SHRINK_STEPS):
        K = K0.copy()
        K[0, 2] = K0[0, 2] - (0.5 * (lo_x + hi_x) - 0.5 * (W - 1))
        K[1, 2] = K0[1, 2] - (0.5 * (lo_y + hi_y) - 0.5 * (H - 1))
        src = _source_pixels(_frame_border(W, H), K, K_P, K_L, d)
        out_x = np.any(~((src[:, 0] >= -_INSIDE_PX) & (src[:, 0] <= w - 1 + _INSIDE_PX)))
        out_y = np.any(~((src[:, 1] >= -_INSIDE_PX) & (src[:, 1] <= h - 1 + _INSIDE_PX)))
        if not (out_x or out_y):
            return K, (W, H), None
        if (out_x and W - 2 < least[0]) or (out_y and H - 2 < least[1]):
            break
        W, H = W - 2 * out_x, H - 2 * out_y
    return K, (W, H), (f"{name}: the lens leaves less than {cfg.min_scale:g} of the frame free of blank pixels; "
                       f"the undistorted image ({W}x{H}) has black borders")


def _frame_border(W: int, H: int) -> np.ndarray:
    """The pixel centres (N, 2) along the border of a W x H image."""
    xs, ys = np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64)
    return np.vstack([np.column_stack([xs, np.zeros(W)]), np.column_stack([xs, np.full(W, H - 1.0)]),
                      np.column_stack([np.zeros(H), ys]), np.column_stack([np.full(H, W - 1.0), ys])])


def undistortion_maps_to(K: np.ndarray, size: tuple[int, int], K_P: np.ndarray, K_L: np.ndarray,
                         d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (H, W) float32 x and y: where each pixel of the PINHOLE image K of ``size``
    samples the photo, :func:`_source_pixels` for every pixel. OpenCV's initUndistortRectifyMap
    with R = K_P^-1 K_L (its R is any 3x3: inv(K R) = K_L^-1 K_P K^-1); OpenCV drops a skew of
    K_L, so such a lens is mapped by the model itself, row block by row block."""
    W, H = int(size[0]), int(size[1])
    if K_L[0, 1] == 0.0:
        return cv2.initUndistortRectifyMap(K_L, d, np.linalg.solve(K_P, K_L), K, (W, H), cv2.CV_32FC1)
    mx, my = np.empty((H, W), np.float32), np.empty((H, W), np.float32)
    xs = np.arange(W, dtype=np.float64)
    rows = max(1, (1 << 20) // max(W, 1))  # a million pixels a block: bounded memory for any photo
    for y0 in range(0, H, rows):
        ys = np.arange(y0, min(H, y0 + rows), dtype=np.float64)
        q = np.column_stack([np.tile(xs, len(ys)), np.repeat(ys, W)])
        src = _source_pixels(q, K, K_P, K_L, d)
        mx[y0:y0 + len(ys)] = src[:, 0].reshape(len(ys), W)
        my[y0:y0 + len(ys)] = src[:, 1].reshape(len(ys), W)
    return mx, my


def _same(a: np.ndarray | None, b: np.ndarray | None, tol: float) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.shape == b.shape and bool(np.all(np.abs(a - b) <= tol))


def pinhole_images(result: Result, cfg: HandoffConfig = HandoffConfig()) -> tuple[list[PinholeImage], list[str]]:
    """The images a trainer gets (:func:`handed_off`), each with its PINHOLE camera (one per
    distinct intrinsics and lens: the first image of each fixes its frame), and the warnings."""
    chosen, warnings = handed_off(result)
    lens_K = result.distortion_K or [None] * len(result.names)
    groups: list[tuple[tuple, np.ndarray, tuple[int, int]]] = []  # (key, K, size) per camera
    images = []
    for i in chosen:
        K_P = Camera(result.P[i]).K
        d = result.distortion[i] if result.distortion else None
        has_lens = d is not None and bool(np.any(d != 0))
        K_L = (lens_K[i] if lens_K[i] is not None else K_P) if has_lens else None
        key = (result.sizes[i], K_P[[0, 0, 0, 1, 1], [0, 1, 2, 1, 2]],
               None if K_L is None else K_L[[0, 0, 0, 1, 1], [0, 1, 2, 1, 2]], d if has_lens else None)
        camera = next((c for c, (k, _, _) in enumerate(groups) if k[0] == key[0] and _same(k[3], key[3], 0.0)
                       and _same(k[1], key[1], cfg.same_intrinsics_px) and _same(k[2], key[2], cfg.same_intrinsics_px)),
                      None)
        if camera is None:
            camera = len(groups)
            if has_lens:
                K, size, note = undistorted_frame(K_P, K_L, d, result.sizes[i], cfg, result.names[i])
            else:
                K, size = _no_skew(K_P), result.sizes[i]
                note = skew_warning(result.names[i], K_P, size, "PINHOLE camera")
            groups.append((key, K, size))
            if note:
                warnings.append(note)
        K, size = groups[camera][1], groups[camera][2]
        to_pinhole = K @ np.linalg.inv(K_P) if has_lens else np.eye(3)
        images.append(PinholeImage(i, K, size, camera, to_pinhole, (K_P, K_L, d) if has_lens else None))
    return images, warnings


def _pinhole_keypoints(result: Result, image: PinholeImage) -> np.ndarray:
    """The image's keypoints (K, 2) in its PINHOLE image's pixels."""
    xy = result.keypoints(image.index)
    if image.lens is None:
        return xy
    p = to_homogeneous(xy) @ image.to_pinhole.T
    return p[:, :2] / p[:, 2:]


def _photos(result: Result, sources: list[str | Path], images: list[PinholeImage]) -> dict[int, Path]:
    """The photo of each image, found by name among ``sources`` (folders, list files or images,
    as reconstruct takes them; a video's keyframes are in the result's keyframes/), its size
    checked where its header tells it."""
    found: dict[str, Path] = {}
    every: list[Path] = []
    keyframes = result.folder / "keyframes"
    for source in [*map(Path, sources), *([keyframes] if keyframes.is_dir() else [])]:
        suffix = source.suffix.lower()
        if source.is_file() and suffix in VIDEO_EXTENSIONS:
            continue  # its keyframes are the result's
        paths = [source] if source.is_file() and suffix in IMAGE_EXTENSIONS else list_images(source)
        every.extend(paths)
        for p in paths:
            found.setdefault(p.name, p)
    unnamed = [im.index for im in images if result.names[im.index] not in found]
    if unnamed:  # a rig's images are renamed by the run (cam0/7.jpg is cam0_7.jpg): the record knows them
        found.update((result.names[i], p) for i, p in renamed_photos(result.folder, result.names, unnamed,
                                                                     every).items())
    missing = [result.names[im.index] for im in images if result.names[im.index] not in found]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        where = ", ".join(map(str, sources)) if sources else "no --images given"
        raise StereoseedError(f"{missing[0]}{more}: no such photo among the images ({where}); give --images the "
                              f"folder or list of images reconstruct read")
    photos = {}
    for im in images:
        path = found[result.names[im.index]]
        _check_size(path, header_size(path), result.sizes[im.index])
        photos[im.index] = path
    return photos


def _check_size(path: Path, size: tuple[int, int] | None, expected: tuple[int, int]) -> None:
    if size is not None and tuple(size) != tuple(expected):
        raise StereoseedError(f"{path}: {size[0]}x{size[1]} pixels, but the result's image of this name is "
                              f"{expected[0]}x{expected[1]}; give --images the photos the run read")


def _write_images(result: Result, images: list[PinholeImage], photos: dict[int, Path], folder: Path) -> list[Path]:
    """Each image into ``folder`` under its name: the photo resampled through its PINHOLE camera
    (the maps made once per camera), or copied byte for byte when it is kept."""
    maps: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    written = []
    for im in images:
        target = folder / result.names[im.index]
        if im.lens is None:
            copy_as_read(photos[im.index], target)
        else:
            photo = read_image(photos[im.index])
            _check_size(photos[im.index], photo.shape[1::-1], result.sizes[im.index])
            if im.camera not in maps:
                maps[im.camera] = undistortion_maps_to(im.K, im.size, *im.lens)
            write_image(target, cv2.remap(photo, *maps[im.camera], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT))
        written.append(target)
    return written


# the EXIF block of a photo sits in its first segments, before any pixel data
_EXIF_WITHIN_BYTES = 2**16


def copy_as_read(photo: Path, target: Path) -> None:
    """``photo`` copied byte for byte to ``target``, unless its EXIF orientation turns it when it
    is read (as stereoseed read it, and its cameras are of the turned image): then its turned
    pixels are written, which a reader that ignores EXIF sees the same way."""
    with open(photo, "rb") as f:
        head = f.read(_EXIF_WITHIN_BYTES)
    if b"Exif" in head:
        data = np.fromfile(photo, np.uint8)
        turned = cv2.imdecode(data, cv2.IMREAD_COLOR)
        raw = cv2.imdecode(data, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        if turned is not None and raw is not None and (turned.shape != raw.shape or not np.array_equal(turned, raw)):
            write_image(target, turned)
            return
    with atomic_path(target) as tmp:
        shutil.copyfile(photo, tmp)


def _prepare(result: Result, out: Path, fmt: str, image_sources, force: bool, cfg: HandoffConfig,
             any_space: bool, files: list[str]) -> tuple[list[PinholeImage], list[str], dict[int, Path]]:
    """What both hand-offs do before writing: the names checked, the images and their cameras,
    the photos found, the folder claimed for the images and ``files`` (every check before the
    first file is written)."""
    check_names(result, fmt, any_space=any_space,
                space_hint="export with --binary (COLMAP's binary model holds it), or rename the image")
    images, warnings = pinhole_images(result, cfg)
    # --images overrides the run's record of its photos; a result without one needs --images
    photos = None if image_sources else recorded_photos(result.folder, result.names, [im.index for im in images])
    if photos is None:
        photos = _photos(result, list(image_sources or []), images)
    for im in images:  # --force replaces the export's files: never the photos it reads
        if (out / "images" / result.names[im.index]).resolve() == photos[im.index].resolve():
            raise StereoseedError(f"{photos[im.index]}: the export would write over the photo it reads; give --out "
                                  f"another folder")
    claim_folder(out, force, [f"images/{result.names[im.index]}" for im in images] + files)
    return images, warnings, photos


def write_colmap_undistorted(result: Result, out_dir: str | Path, image_sources=(), binary: bool = False,
                             force: bool = False, cfg: HandoffConfig = HandoffConfig()) -> Handoff:
    """COLMAP's undistorted workspace in out_dir: ``images/`` (the photos undistorted, or copied
    without a lens) and ``sparse/0/{cameras,images,points3D}.{txt|bin}`` with a PINHOLE camera per
    distinct intrinsics, every 2D point in the new images' pixels (COLMAP's convention, +0.5)."""
    out = Path(out_dir)
    fmt = "COLMAP's binary model" if binary else "COLMAP's text model"
    sparse = [f"sparse/0/{name}" for name in colmap_files(binary)]
    images, warnings, photos = _prepare(result, out, fmt, image_sources, force, cfg, any_space=not binary, files=sparse)
    stale = other_colmap_model(out, "sparse/0", binary) if out.is_dir() else []
    record_written(out, [f"images/{result.names[im.index]}" for im in images] + sparse)
    written = _write_images(result, images, photos, out / "images")
    cameras: dict[int, tuple] = {}
    for im in images:
        cameras.setdefault(im.camera, (im.camera + 1, "PINHOLE", im.size[0], im.size[1],
                                       [float(v) for v in (im.K[0, 0], im.K[1, 1], im.K[0, 2] + 0.5, im.K[1, 2] + 0.5)]))
    image_id = np.zeros(len(result.names), np.int64)
    tr = result.tracks
    point_of = point_ids(result, [im.index for im in images])
    rows = []
    for n, im in enumerate(images, 1):
        image_id[im.index] = n
        ids = point_of[im.index]
        _, R, t = Camera(result.P[im.index]).krt
        rows.append((n, quaternion_from_rotation(R), t, im.camera + 1, result.names[im.index],
                     _pinhole_keypoints(result, im) + 0.5, ids))
    tracks = tracks_by_point(result, image_id)
    cams = [cameras[c] for c in sorted(cameras)]
    if binary:
        write_colmap_binary(out / "sparse" / "0", cams, rows, tr, tracks)
    else:
        flagged = tuple(result.names[i] for i in flagged_images(result) if image_id[i])
        write_colmap_text(out / "sparse" / "0", cams, rows, tr, tracks, flagged)
    written += [out / p for p in sparse]
    remove_written(out, stale)
    return Handoff(len(images), len(cameras), len(tr["point_xyz"]), any(im.lens is not None for im in images),
                   written, logged(result.warnings + warnings))


def camera_to_world_gl(P: np.ndarray) -> np.ndarray:
    """(4, 4) camera-to-world of camera P (3, 4) with OpenGL's camera axes (x right, y up, z
    back), nerfstudio's ``transform_matrix``."""
    _, R, t = Camera(P).krt
    c2w = np.eye(4)
    c2w[:3, :3] = R.T @ np.diag([1.0, -1.0, -1.0])
    c2w[:3, 3] = -R.T @ t
    return c2w


def write_nerfstudio(result: Result, out_dir: str | Path, image_sources=(), force: bool = False,
                     cfg: HandoffConfig = HandoffConfig()) -> Handoff:
    """nerfstudio's data folder in out_dir: ``transforms.json`` (camera_model PINHOLE; fl_x,
    fl_y, cx, cy (pixel centres at +0.5, as nerfstudio casts its rays), w, h at the top level
    when every frame shares them, else per frame; per frame ``file_path`` and the camera-to-world
    ``transform_matrix`` in OpenGL's camera axes, the world the result's), ``images/`` (as the
    COLMAP hand-off writes them) and the sparse cloud with its colours as ``ply_file_path``."""
    out = Path(out_dir)
    images, warnings, photos = _prepare(result, out, "nerfstudio's transforms.json", image_sources, force, cfg,
                                        any_space=False, files=["transforms.json", NERFSTUDIO_PLY])
    record_written(out, [f"images/{result.names[im.index]}" for im in images] + ["transforms.json", NERFSTUDIO_PLY])
    written = _write_images(result, images, photos, out / "images")
    shared = len({im.camera for im in images}) == 1

    def intrinsics(im: PinholeImage) -> dict:
        return {"fl_x": float(im.K[0, 0]), "fl_y": float(im.K[1, 1]), "cx": float(im.K[0, 2] + 0.5),
                "cy": float(im.K[1, 2] + 0.5), "w": int(im.size[0]), "h": int(im.size[1])}

    frames = [{"file_path": f"images/{result.names[im.index]}",
               "transform_matrix": camera_to_world_gl(result.P[im.index]).tolist(),
               **({} if shared else intrinsics(im))} for im in images]
    tr = result.tracks
    written.append(write_ply(out / NERFSTUDIO_PLY, tr["point_xyz"], tr["point_rgb"]))
    meta = {"camera_model": "PINHOLE", **(intrinsics(images[0]) if shared and images else {}), "frames": frames,
            "ply_file_path": NERFSTUDIO_PLY}
    written.append(write_json(out / "transforms.json", meta))
    return Handoff(len(images), len({im.camera for im in images}), len(tr["point_xyz"]),
                   any(im.lens is not None for im in images), written, logged(result.warnings + warnings))
