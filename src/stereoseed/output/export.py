"""Exports of a result folder for the field's tools: COLMAP's model (text or binary), VisualSFM's
NVM and Bundler's bundle.out (the reader of COLMAP models is :mod:`stereoseed.io.colmap`; the
hand-offs with undistorted images, for Gaussian-splatting and nerfstudio, are
:mod:`stereoseed.output.handoff`).

An export writes into a folder of its own: a folder holding files it did not write (its
manifest ``.stereoseed-export.json`` lists those it wrote) is refused unless ``force``, and even
then a file of the export's names that it did not write is refused, never replaced; each file is
written atomically. An image name a format cannot hold (a line break, a control character; a
space in COLMAP's text model and NVM, a leading or trailing one in Bundler's list) is refused with
its name.

Conventions (docs/formats.md): COLMAP's pixel (0, 0) is the top-left *corner* of the top-left
pixel (ours: its centre), so principal points and 2D points move by +0.5 px; its quaternion
(qw, qx, qy, qz) and t are world-to-camera (ours too); one COLMAP camera per image, since the
moving camera may zoom. Our 11-DOF cameras may have skew, which no COLMAP model has: the
nearest zero-skew camera is written and a warning says by how much.
"""
from __future__ import annotations

import logging
import os
import struct
from pathlib import Path
from typing import Iterable

import numpy as np

from stereoseed.errors import StereoseedError
from stereoseed.geometry.camera import Camera
from stereoseed.geometry.lens import distort_pixels
from stereoseed.geometry.models import quaternion_from_rotation
from stereoseed.io.colmap import COLMAP_MODELS
from stereoseed.io.files import atomic_path, name_trouble, write_json, write_text
from stereoseed.output.reader import Result
from stereoseed.output.result_set import read_manifest

__all__ = ["write_colmap", "write_nvm", "write_bundler", "colmap_camera", "EXPORT_MANIFEST", "claim_folder",
           "record_written", "other_colmap_model", "remove_written", "check_names", "write_colmap_text", "write_colmap_binary", "tracks_by_point",
           "observations_by_point", "flagged_images", "flagged_warnings", "logged", "moved_px", "skew_warning",
           "colmap_files"]

log = logging.getLogger(__name__)

_SAME_FOCAL = 1e-9  # relative difference under which fx and fy are one focal length
# an approximation of a camera by a simpler model (no skew, one focal length) is said when it
# moves a pixel by more than this: a tenth of a pixel, below the matches' own error
MAX_APPROXIMATION_PX = 0.1


EXPORT_MANIFEST = ".stereoseed-export.json"  # the files the exports wrote into the folder


def _written_before(folder: Path) -> set[str]:
    return read_manifest(folder / EXPORT_MANIFEST) or set()


def claim_folder(folder: Path, force: bool, names: list[str] = ()) -> None:
    """Refuse, before writing, an output folder that holds anything the exports did not write
    (unless ``force``: the export then writes beside the other files). Even with ``force``, a
    file of one of ``names`` (what this export writes, relative to ``folder``) that the exports
    did not write is refused, never replaced. A sub-folder is the export's when every file in it
    is (``images/``, ``sparse/0/``)."""
    if folder.exists() and not folder.is_dir():
        raise StereoseedError(f"{folder}: exists and is not a folder; give a folder for the export")
    if not folder.is_dir():
        return
    ours = _written_before(folder) | {EXPORT_MANIFEST}
    if force:
        for rel in _present(folder, names):
            if rel not in ours:
                raise StereoseedError(f"{folder / rel}: stereoseed export did not write it, and --force replaces only "
                                      f"the export's own files; move it away or give another --out")
        return
    foreign = sorted(e.name + ("/" if e.is_dir() else "") for e in folder.iterdir() if not _ours(e, folder, ours))
    if foreign:
        more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
        raise StereoseedError(f"{folder}: holds files stereoseed export did not write ({', '.join(foreign[:3])}{more}); "
                              f"give an empty or new folder, or --force to write beside them (never over them)")


def _present(folder: Path, names: Iterable[str]) -> list[str]:
    """The ``names`` (relative to ``folder``) something stands at: a file, a folder, or a link, even
    a broken one."""
    return [rel for rel in names if (folder / rel).exists() or (folder / rel).is_symlink()]


def _ours(entry: Path, folder: Path, ours: set[str]) -> bool:
    """Whether ``entry`` of the export folder is the exports': a file the manifest lists, or a
    real folder holding only such files (the walk stops at the first other one)."""
    if entry.is_symlink() or not entry.is_dir():
        return entry.relative_to(folder).as_posix() in ours
    for root, dirs, files in os.walk(entry):
        here = Path(root)
        for name in files + [d for d in dirs if (here / d).is_symlink()]:
            if (here / name).relative_to(folder).as_posix() not in ours:
                return False
    return True


def record_written(folder: Path, files: list[str], removed: list[str] = ()) -> None:
    """Add ``files`` (paths relative to ``folder``, with ``/``) to the folder's export manifest
    (and take the ``removed`` ones out)."""
    write_json(folder / EXPORT_MANIFEST, {"files": sorted((_written_before(folder) | set(files)) - set(removed))})


def other_colmap_model(folder: Path, model: str, binary: bool) -> list[str]:
    """The files of the other COLMAP format in ``folder / model`` (paths relative to ``folder``):
    COLMAP reads a folder's binary model before its text one, so a stale model of the other
    format would be read instead of this export. Refused (even with ``force``) when the export
    did not write one of them; the caller removes them once its own model is written
    (:func:`remove_written`)."""
    ours = _written_before(folder)
    stale = _present(folder, [f"{model}/{name}".lstrip("/") for name in colmap_files(not binary)])
    for rel in stale:
        if rel not in ours:
            raise StereoseedError(f"{folder / rel}: a COLMAP model stereoseed export did not write; COLMAP would read "
                                  f"it instead of this {'binary' if binary else 'text'} export; move it away or give "
                                  f"another --out")
    return stale


def remove_written(folder: Path, files: list[str]) -> None:
    """Remove ``files`` the export wrote (relative to ``folder``) and take them off its manifest."""
    for rel in files:
        (folder / rel).unlink(missing_ok=True)
    if files:
        record_written(folder, [], removed=files)


def check_names(result: Result, fmt: str, edge_space: bool = False, any_space: bool = False,
                 space_hint: str = "") -> None:
    """Refuse a registered image whose name ``fmt`` cannot hold, or two images of one name."""
    seen: set[str] = set()
    for i in result.registered:
        name = result.names[i]
        trouble = name_trouble(name)
        hint = "rename the image and reconstruct again"
        if trouble is None and any_space and any(c.isspace() for c in name):
            trouble = "a space (the format separates its fields by spaces)"
            hint = space_hint or hint
        elif trouble is None and edge_space and name != name.strip():
            trouble = "a space at its start or end (the format trims it)"
        if trouble is None and name in seen:
            trouble = "the name of another image (the format finds images by name)"
        if trouble:
            shown = repr(name)[1:-1]
            raise StereoseedError(f"{result.folder}: the image name '{shown[:80]}' holds {trouble}, which {fmt} cannot "
                                  f"hold; {hint}")
        seen.add(name)


def _num(v: float) -> str:
    """A number as text with every digit of its float64 value."""
    return repr(float(v))


def moved_px(K: np.ndarray, size: tuple[int, int], drop_skew: bool = True, one_focal: bool = False) -> float:
    """How far (px, at worst over the image) a pixel moves when K (3, 3) loses its skew and,
    with ``one_focal``, takes the mean of fx and fy."""
    w, h = size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    y = (corners[:, 1] - K[1, 2]) / K[1, 1]
    x = (corners[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    f = 0.5 * (K[0, 0] + K[1, 1])
    fx, fy = (f, f) if one_focal else (K[0, 0], K[1, 1])
    moved = np.stack([fx * x + K[0, 2], fy * y + K[1, 2]], axis=1) - corners
    return float(np.max(np.linalg.norm(moved, axis=1)))


def skew_warning(name: str, K: np.ndarray, size: tuple[int, int], written: str) -> str | None:
    """Why the zero-skew camera written for ``K`` (3, 3) of an image of ``size`` is an
    approximation (its pixels move by more than ``MAX_APPROXIMATION_PX``), or None. written: what
    has no skew ("COLMAP model", "PINHOLE camera")."""
    moved = moved_px(K, size)
    if moved <= MAX_APPROXIMATION_PX:
        return None
    return (f"{name}: the camera has skew {K[0, 1] / K[0, 0]:+.2e} (relative to f), which no {written} has; the "
            f"nearest zero-skew camera is written (pixels move by up to {moved:.2f} px)")


def colmap_camera(P: np.ndarray, size: tuple[int, int], name: str = "", distortion: np.ndarray | None = None
                  ) -> tuple[str, list[float], np.ndarray, np.ndarray, str | None]:
    """COLMAP's view of camera P (3, 4) (ours) of an image of ``size`` (width, height): (model,
    params in COLMAP's pixel convention, quaternion (4,) w x y z, t (3,), warning or None).
    SIMPLE_PINHOLE when fx = fy, else PINHOLE; a skewed camera loses its skew, with a warning
    when that moves a pixel by more than ``MAX_APPROXIMATION_PX``."""
    K, R, t = Camera(P).krt
    warning = skew_warning(name, K, size, "COLMAP model")
    cx, cy = K[0, 2] + 0.5, K[1, 2] + 0.5
    if distortion is not None and np.any(distortion != 0):
        k1, k2, p1, p2, k3 = distortion
        model, params = ("OPENCV", [K[0, 0], K[1, 1], cx, cy, k1, k2, p1, p2]) if k3 == 0 else \
            ("FULL_OPENCV", [K[0, 0], K[1, 1], cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0])
    elif abs(K[0, 0] - K[1, 1]) <= _SAME_FOCAL * K[0, 0]:
        model, params = "SIMPLE_PINHOLE", [K[0, 0], cx, cy]
    else:
        model, params = "PINHOLE", [K[0, 0], K[1, 1], cx, cy]
    q = quaternion_from_rotation(R)
    return model, [float(p) for p in params], q, t, warning


def point_ids(result: Result, images: list[int]) -> dict[int, np.ndarray]:
    """{image: (K,) the 1-based COLMAP point id of each of its keypoints, -1 for none} of the
    ``images``, in one pass over the observations (grouped by image)."""
    tr = result.tracks
    order = np.argsort(tr["obs_image"], kind="stable")
    ends = np.searchsorted(tr["obs_image"][order], [images, np.add(images, 1)]) if len(images) else ([], [])
    out = {}
    for i, a, b in zip(images, *ends):
        ids = np.full(len(result.keypoints(i)), -1, np.int64)
        here = order[a:b]
        ids[tr["obs_keypoint"][here]] = tr["obs_point"][here] + 1
        out[i] = ids
    return out


def _colmap_model(result: Result) -> tuple[list, list, list[str]]:
    """(cameras [(id, model, w, h, params)], images [(id, q, t, camera id, name, xy (K, 2), point ids (K,))],
    warnings) with COLMAP's 1-based ids and pixel convention."""
    cameras, images, warnings = [], [], []
    point_of = point_ids(result, result.registered)
    for n, i in enumerate(result.registered, 1):
        lens = result.distortion[i] if result.distortion else None
        model, params, q, t, warning = colmap_camera(result.P[i], result.sizes[i], result.names[i], lens)
        if warning:
            warnings.append(warning)
        w, h = result.sizes[i]
        cameras.append((n, model, w, h, params))
        xy = result.keypoints(i)
        if lens is not None:  # the keypoints are in the undistorted image; COLMAP's model distorts
            K = Camera(result.P[i]).K
            xy = distort_pixels(xy, K, lens)
        images.append((n, q, t, n, result.names[i], xy + 0.5, point_of[i]))
    return cameras, images, warnings


def observations_by_point(result: Result) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The observations grouped by point: (starts (P + 1,): point p's are rows starts[p] to
    starts[p + 1]; image (O,), keypoint (O,), xy (O, 2) in our pixel convention)."""
    tr = result.tracks
    order = np.argsort(tr["obs_point"], kind="stable")
    image, keypoint = tr["obs_image"][order], tr["obs_keypoint"][order]
    xy = tr["keypoints_xy"][tr["keypoints_offset"][image] + keypoint]
    starts = np.zeros(len(tr["point_xyz"]) + 1, np.int64)
    np.cumsum(np.bincount(tr["obs_point"], minlength=len(tr["point_xyz"])), out=starts[1:])
    return starts, image, keypoint, xy


def tracks_by_point(result: Result, image_id: np.ndarray | None = None) -> list[np.ndarray]:
    """Per point, its track (T, 2): (COLMAP image id, 2D point index). ``image_id`` (n_images,):
    each image's COLMAP id (default: the registered images numbered from 1 in order)."""
    if image_id is None:
        image_id = np.zeros(len(result.names), np.int64)
        image_id[result.registered] = np.arange(1, len(result.registered) + 1)
    starts, image, keypoint, _ = observations_by_point(result)
    return np.split(np.stack([image_id[image], keypoint], axis=1), starts[1:-1])


def colmap_files(binary: bool) -> list[str]:
    """The three files of a COLMAP model, binary (.bin) or text (.txt)."""
    return [f"{n}.{'bin' if binary else 'txt'}" for n in ("cameras", "images", "points3D")]


def write_colmap(result: Result, out_dir: str | Path, binary: bool = False, force: bool = False) -> list[str]:
    """COLMAP's sparse model (cameras, images with every 2D point, points3D with colour, error
    and track) in out_dir, as .txt or .bin files. Returns the warnings (also logged): the
    images left out and why, the approximations made."""
    out = Path(out_dir)
    # COLMAP's text reader ends a name at its first space (pycolmap 3.x reads "a b.png" as "a")
    check_names(result, "COLMAP's binary model" if binary else "COLMAP's text model", any_space=not binary,
                 space_hint="export with --binary (COLMAP's binary model holds it), or rename the image")
    claim_folder(out, force, colmap_files(binary))
    stale = other_colmap_model(out, "", binary) if out.is_dir() else []
    cameras, images, warnings = _colmap_model(result)
    tr = result.tracks
    tracks = tracks_by_point(result)
    if binary:
        write_colmap_binary(out, cameras, images, tr, tracks)
    else:
        write_colmap_text(out, cameras, images, tr, tracks, tuple(result.names[i] for i in flagged_images(result)))
    record_written(out, colmap_files(binary))
    remove_written(out, stale)
    return logged(result.warnings + warnings + flagged_warnings(result))


def write_colmap_text(out: Path, cameras, images, tr, tracks, flagged: tuple[str, ...] = ()) -> None:
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]", f"# Number of cameras: {len(cameras)}"]
    lines += [f"{c} {m} {w} {h} " + " ".join(repr(p) for p in params) for c, m, w, h, params in cameras]
    write_text(out / "cameras.txt", "\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)", f"# Number of images: {len(images)}"]
    lines += [f"# flagged by stereoseed (not vouched for, see cameras.json): {name}" for name in flagged]
    for n, q, t, cam, name, xy, pid in images:
        lines.append(f"{n} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" {cam} {name}")
        lines.append(" ".join(f"{x!r} {y!r} {p}" for (x, y), p in zip(xy.tolist(), pid.tolist())))
    write_text(out / "images.txt", "\n".join(lines) + "\n")
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {len(tracks)}"]
    for p, track in enumerate(tracks):
        X, rgb = tr["point_xyz"][p], tr["point_rgb"][p]
        lines.append(f"{p + 1} {_num(X[0])} {_num(X[1])} {_num(X[2])} {rgb[0]} {rgb[1]} {rgb[2]} {float(tr['point_error'][p])!r} "
                     + " ".join(f"{i} {k}" for i, k in track.tolist()))
    write_text(out / "points3D.txt", "\n".join(lines) + "\n")


def write_colmap_binary(out: Path, cameras, images, tr, tracks) -> None:
    def write(name: str, chunks: list[bytes]) -> None:
        with atomic_path(out / name) as tmp:
            tmp.write_bytes(b"".join(chunks))

    write("cameras.bin", [struct.pack("<Q", len(cameras))] + [
        struct.pack("<iiQQ", c, COLMAP_MODELS[m][0], w, h) + struct.pack(f"<{len(params)}d", *params)
        for c, m, w, h, params in cameras])
    chunks = [struct.pack("<Q", len(images))]
    for n, q, t, cam, name, xy, pid in images:
        chunks.append(struct.pack("<i7di", n, *q, *t, cam) + name.encode("utf-8") + b"\0")
        rows = np.empty(len(xy), dtype=[("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
        rows["x"], rows["y"], rows["id"] = xy[:, 0], xy[:, 1], pid
        chunks += [struct.pack("<Q", len(xy)), rows.tobytes()]
    write("images.bin", chunks)
    chunks = [struct.pack("<Q", len(tracks))]
    for p, track in enumerate(tracks):
        X, rgb = tr["point_xyz"][p], tr["point_rgb"][p]
        chunks.append(struct.pack("<Q3d3Bd", p + 1, *X, *(int(c) for c in rgb), float(tr["point_error"][p]))
                      + struct.pack("<Q", len(track)) + np.asarray(track, "<i4").tobytes())
    write("points3D.bin", chunks)


def _single_focal_cameras(result: Result, fmt: str) -> tuple[dict[int, tuple], list[str]]:
    """Per registered image, (one focal length: the mean of fx and fy, R, t, principal point
    (2,)) for a format with one focal length and no skew; a warning for each image where that
    moves a pixel by more than ``MAX_APPROXIMATION_PX``."""
    cams, warnings = {}, []
    for i in result.registered:
        K, R, t = Camera(result.P[i]).krt
        moved = moved_px(K, result.sizes[i], one_focal=True)
        if moved > MAX_APPROXIMATION_PX:
            warnings.append(f"{result.names[i]}: {fmt} has one focal length and no skew; fx, fy averaged "
                            f"(pixels move by up to {moved:.2f} px)")
        cams[i] = (0.5 * (K[0, 0] + K[1, 1]), R, t, K[:2, 2])
    return cams, warnings


def _measurements(result: Result, cams: dict[int, tuple], y_up: bool) -> list[str]:
    """Per point, its measurements "camera keypoint dx dy", relative to each camera's principal
    point (y up for Bundler), the cameras numbered in registration order."""
    index = {i: n for n, i in enumerate(result.registered)}
    starts, image, keypoint, xy = observations_by_point(result)
    return [" ".join(f"{index[i]} {k} {_num(x - cams[i][3][0])} "
                     f"{_num(cams[i][3][1] - y if y_up else y - cams[i][3][1])}"
                     for i, k, (x, y) in zip(image[a:b].tolist(), keypoint[a:b].tolist(), xy[a:b].tolist()))
            for a, b in zip(starts[:-1], starts[1:])]


def write_nvm(result: Result, path: str | Path, force: bool = False) -> list[str]:
    """VisualSFM's NVM_V3: one focal length per camera (the mean of fx, fy), the principal
    point assumed at the measurement origin, so measurements are written relative to each
    camera's principal point. Returns the warnings."""
    path = Path(path)
    check_names(result, "NVM", any_space=True)
    claim_folder(path.parent, force, [path.name])
    tr = result.tracks
    cams, warnings = _single_focal_cameras(result, "NVM")
    lines = ["NVM_V3", "", str(len(cams))]
    for i, (f, R, t, _) in cams.items():
        w, x, y, z = quaternion_from_rotation(R)
        lines.append(f"{result.names[i]} {_num(f)} " + " ".join(_num(v) for v in (w, x, y, z, *(-R.T @ t))) + " 0 0")
    lines.append(str(len(tr["point_xyz"])))
    counts = np.diff(observations_by_point(result)[0])
    for X, rgb, n, meas in zip(tr["point_xyz"], tr["point_rgb"], counts, _measurements(result, cams, y_up=False)):
        lines.append(f"{_num(X[0])} {_num(X[1])} {_num(X[2])} {rgb[0]} {rgb[1]} {rgb[2]} {n} {meas}")
    write_text(path, "\n".join(lines) + "\n")
    record_written(path.parent, [path.name])
    return logged(result.warnings + warnings + flagged_warnings(result))


def write_bundler(result: Result, out_dir: str | Path, force: bool = False) -> list[str]:
    """Bundler's bundle.out (v0.3) and list.txt: cameras look down -z with y up, measurements
    relative to the principal point with y up. Returns the warnings."""
    out, tr = Path(out_dir), result.tracks
    check_names(result, "Bundler's list.txt", edge_space=True)
    claim_folder(out, force, ["bundle.out", "list.txt"])
    cams, warnings = _single_focal_cameras(result, "Bundler")
    flip = np.diag([1.0, -1.0, -1.0])
    lines = ["# Bundle file v0.3", f"{len(cams)} {len(tr['point_xyz'])}"]
    for f, R, t, _ in cams.values():
        lines.append(f"{_num(f)} 0 0")
        lines += [" ".join(_num(v) for v in row) for row in flip @ R]
        lines.append(" ".join(_num(v) for v in flip @ t))
    counts = np.diff(observations_by_point(result)[0])
    for X, rgb, n, meas in zip(tr["point_xyz"], tr["point_rgb"], counts, _measurements(result, cams, y_up=True)):
        lines += [" ".join(_num(v) for v in X), f"{rgb[0]} {rgb[1]} {rgb[2]}", f"{n} {meas}"]
    write_text(out / "bundle.out", "\n".join(lines) + "\n")
    write_text(out / "list.txt", "\n".join(result.names[i] for i in result.registered) + "\n")
    record_written(out, ["bundle.out", "list.txt"])
    return logged(result.warnings + warnings + flagged_warnings(result))


def flagged_images(result: Result) -> list[int]:
    """The exported images whose camera the run flagged."""
    return [i for i, why in enumerate(result.flags) if why is not None and result.P[i] is not None]


def flagged_warnings(result: Result) -> list[str]:
    """What an export says of the cameras the run flagged: exported, not vouched for."""
    return [f"{result.names[i]}: flagged by the run ({result.flags[i]}); exported, but stereoseed does not vouch "
            f"for this camera" for i in flagged_images(result)]


def logged(warnings: list[str]) -> list[str]:
    """The warnings, also logged (the CLI prints what it gets back)."""
    for w in warnings:
        log.info("%s", w)
    return warnings
