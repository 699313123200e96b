"""A result folder read back (cameras.json, tracks.npz) as a :class:`Result`: the input of the
exports (:mod:`stereoseed.output.export`).

Whatever the folder holds, :func:`load_result` gives a :class:`Result` every export can write
or a :class:`StereoseedError` of one line: the JSON's types, every array's dtype and shape, and
every index against cameras.json are checked (an archive is read as numbers only, never as
pickled objects). A registered image whose camera is not finite or not a camera is left out,
with a warning in :attr:`Result.warnings`, with its observations.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stereoseed.errors import StereoseedError
from stereoseed.output.results import FORMAT_VERSION

__all__ = ["Result", "load_result"]

log = logging.getLogger(__name__)

# a camera whose left 3x3 block is this near singular (smallest over largest singular value) is none
_SINGULAR = 1e-10
_MAX_SIDE = 1 << 20  # pixels: no image is wider or taller


@dataclass
class Result:
    """A result folder read back: per image (in input order) name, (width, height), P (3, 4) in
    the input image's frame or None; the points and their tracks (tracks.npz's arrays)."""

    folder: Path
    names: list[str]
    sizes: list[tuple[int, int]]
    P: list[np.ndarray | None]
    tracks: dict[str, np.ndarray]
    distortion: list[np.ndarray | None] = field(default_factory=list)  # the lens, where the run undistorted
    warnings: list[str] = field(default_factory=list)  # what was left out, and why
    flags: list[str | None] = field(default_factory=list)  # why the run could not vouch for a camera, or None
    # the lens's own K (cameras.json distortion_K: the distortion acts on its pixels), None where
    # the file has none or it is no intrinsic matrix
    distortion_K: list[np.ndarray | None] = field(default_factory=list)

    @property
    def registered(self) -> list[int]:
        return [i for i, P in enumerate(self.P) if P is not None]

    def keypoints(self, image: int) -> np.ndarray:
        """(K, 2) keypoints of image ``image`` (our pixel convention), indexed by obs_keypoint."""
        off = self.tracks["keypoints_offset"]
        return self.tracks["keypoints_xy"][off[image]:off[image + 1]]


class _Bad(Exception):
    """A result file that is not as stereoseed writes it; the message says what."""


def load_result(folder: str | Path) -> Result:
    """Read cameras.json and tracks.npz of a result folder. Raises :class:`StereoseedError`
    naming the missing, unreadable or malformed file and what is wrong in it."""
    folder = Path(folder)
    cams_path, tracks_path = folder / "cameras.json", folder / "tracks.npz"
    for p in (cams_path, tracks_path):
        if not p.is_file():
            raise StereoseedError(f"{folder}: no {p.name}; give a folder written by stereoseed reconstruct "
                                  f"(version {FORMAT_VERSION} or later)")
    again = "give a folder written by stereoseed reconstruct, or run it again"
    try:
        names, sizes, Ps, lens, flags, lens_K = _cameras(cams_path)
    except _Bad as e:
        raise StereoseedError(f"{cams_path}: {e}; {again}") from None
    try:
        tracks = _tracks(tracks_path, len(names), [P is not None for P in Ps])
    except _Bad as e:
        raise StereoseedError(f"{tracks_path}: {e}; {again}") from None
    warnings = []
    for i, P in enumerate(Ps):
        if P is not None and not _is_camera(P):
            warnings.append(f"{names[i]}: its camera in cameras.json is not finite or not a camera; the image is "
                            f"left out of the export")
            Ps[i] = None
    if warnings:
        tracks = _without_images(tracks, [P is not None for P in Ps])
        for w in warnings:
            log.info("%s", w)  # the exports hand them on with their own
    return Result(folder, names, sizes, Ps, tracks, lens, warnings, flags, lens_K)


def _cameras(path: Path) -> tuple[list[str], list[tuple[int, int]], list[np.ndarray | None], list, list, list]:
    """(names, sizes, P or None, lens or None, flag or None, the lens's K or None) per image of
    cameras.json; the flag:
    the flag_reason of a camera marked ``"reliable": false`` (results written before the field
    existed: None)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:
        raise _Bad(f"not readable JSON ({type(e).__name__})") from None
    images = data.get("images") if isinstance(data, dict) else None
    if not isinstance(images, list) or not images:
        raise _Bad('no "images" list')
    names, sizes, Ps, lens, flags, lens_K = [], [], [], [], [], []
    for n, im in enumerate(images):
        where = f"image {n}"
        if not isinstance(im, dict) or not isinstance(im.get("name"), str) or not im["name"]:
            raise _Bad(f"{where} has no name")
        w, h = im.get("width"), im.get("height")
        if not all(isinstance(v, int) and not isinstance(v, bool) and 0 < v <= _MAX_SIDE for v in (w, h)):
            raise _Bad(f"{where} ({im['name']!r}) has no width and height in pixels")
        registered = im.get("registered")
        if not isinstance(registered, bool):
            raise _Bad(f"{where} ({im['name']!r}) does not say whether it is registered")
        P = _numbers(im.get("P"), (3, 4), f"{where}'s P") if registered else None
        d = im.get("distortion")
        lens.append(None if d is None else _numbers(d, None, f"{where}'s distortion"))
        if lens[-1] is not None and (lens[-1].shape[0] not in (4, 5) or not np.all(np.isfinite(lens[-1]))):
            raise _Bad(f"{where}'s distortion is not 4 or 5 finite numbers")
        if lens[-1] is not None and lens[-1].shape[0] == 4:
            lens[-1] = np.append(lens[-1], 0.0)
        names.append(im["name"])
        sizes.append((w, h))
        Ps.append(P)
        flags.append(str(im.get("flag_reason") or "flagged") if im.get("reliable") is False else None)
        lens_K.append(_intrinsic_matrix(im.get("distortion_K")))
    return names, sizes, Ps, lens, flags, lens_K


def _intrinsic_matrix(value: Any) -> np.ndarray | None:
    """``value`` as a (3, 3) intrinsic matrix (finite, positive focal lengths, last row 0 0 1), else None."""
    try:
        K = np.array(value, np.float64).reshape(3, 3)
    except (ValueError, TypeError):
        return None
    good = np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1])
    return K if good else None


def _numbers(value: Any, shape: tuple[int, ...] | None, what: str) -> np.ndarray:
    """A JSON array of numbers (null for NaN is refused) as float64 of ``shape`` (None: a flat list)."""
    try:
        a = np.array(value, dtype=np.float64)
    except (ValueError, TypeError):
        raise _Bad(f"{what} is not an array of numbers") from None
    if (shape is None and a.ndim != 1) or (shape is not None and a.shape != shape):
        raise _Bad(f"{what} is not " + ("a list of numbers" if shape is None else "x".join(map(str, shape))))
    return a


def _is_camera(P: np.ndarray) -> bool:
    """Finite, with a left 3x3 block that is not singular."""
    if not np.all(np.isfinite(P)) or not np.any(P[:, :3]):
        return False
    s = np.linalg.svd(P[:, :3] / np.abs(P[:, :3]).max(), compute_uv=False)
    return bool(s[2] >= _SINGULAR * s[0])


# tracks.npz's arrays: (dtype kind: f float, i integer, u1 uint8; shape, "P", "O", "K", "N+1" the
# lengths they must share)
_TRACKS = {"point_xyz": ("f", ("P", 3)), "point_rgb": ("u1", ("P", 3)), "point_error": ("f", ("P",)),
           "obs_point": ("i", ("O",)), "obs_image": ("i", ("O",)), "obs_keypoint": ("i", ("O",)),
           "keypoints_xy": ("f", ("K", 2)), "keypoints_offset": ("i", ("N+1",))}


# tracks.npz is written compressed, and its coordinates barely compress: its arrays take a few
# times the archive's size unpacked. One whose members declare more than this many times it is no
# archive of ours (a zip bomb inflates a thousandfold), refused before anything is decompressed
MAX_TRACKS_INFLATION = 100
_ANY_RATIO_BYTES = 64 * 2**20  # unpacked sizes below this are read whatever the ratio: little memory


def _refuse_inflation(npz: Any, packed: int) -> None:
    # the sizes the archive's directory declares: zipfile stops a member's output at its size
    unpacked = sum(info.file_size for info in npz.zip.infolist())
    if unpacked > max(_ANY_RATIO_BYTES, MAX_TRACKS_INFLATION * packed):
        raise _Bad(f"its arrays declare {unpacked} bytes unpacked, {unpacked // max(packed, 1)} times the archive "
                   f"(one written by stereoseed: a few times)")


def _tracks(path: Path, n_images: int, registered: list[bool]) -> dict[str, np.ndarray]:
    """tracks.npz's arrays, each of the dtype and shape docs/formats.md gives, every index in range."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            if not isinstance(npz, np.lib.npyio.NpzFile):
                raise _Bad("not an .npz archive")
            _refuse_inflation(npz, path.stat().st_size)  # before a member is decompressed
            tracks = {k: npz[k] for k in npz.files}
    except _Bad:
        raise
    except Exception as e:  # noqa: BLE001 - a damaged archive or .npy header raises whatever NumPy's parsers
        # raise (zipfile, zlib, tokenize, ast, ValueError...): each is a damaged file to the user
        raise _Bad(f"damaged or not an .npz archive ({type(e).__name__}: {str(e)[:60]})") from None
    if tracks.get("format_version") is not None:
        v = tracks["format_version"]
        if v.shape != () or v.dtype.kind not in "iu" or int(v) > FORMAT_VERSION:
            raise _Bad(f"format version {v!r}: written by a newer stereoseed")
    sizes = {"N+1": n_images + 1}
    for name, (kind, shape) in _TRACKS.items():
        a = tracks.get(name)
        if a is None:
            raise _Bad(f"no {name} array")
        good = a.dtype == np.uint8 if kind == "u1" else a.dtype.kind == kind or (kind == "i" and a.dtype.kind == "u")
        if not good or a.ndim != len(shape):
            raise _Bad(f"{name} is {a.dtype} of {a.ndim} dimension(s), not as written")
        for n, s in zip(a.shape, shape):
            if (sizes.setdefault(s, n) if isinstance(s, str) else s) != n:
                raise _Bad(f"{name} has shape {a.shape}, which does not fit the other arrays and the "
                           f"{n_images} images of cameras.json")
    for name in ("point_xyz", "point_error", "keypoints_xy"):
        if not np.all(np.isfinite(tracks[name])):
            raise _Bad(f"{name} holds NaN or infinite values")
    off = tracks["keypoints_offset"].astype(np.int64)
    if off[0] != 0 or np.any(np.diff(off) < 0) or off[-1] != sizes["K"]:
        raise _Bad("keypoints_offset does not index keypoints_xy")
    image, point, key = (tracks[k].astype(np.int64) for k in ("obs_image", "obs_point", "obs_keypoint"))
    if image.size and (image.min() < 0 or image.max() >= n_images):
        raise _Bad("obs_image names an image that cameras.json does not hold")
    if not np.all(np.asarray(registered)[image]):
        raise _Bad("obs_image names an image that cameras.json does not register")
    if point.size and (point.min() < 0 or point.max() >= sizes["P"]):
        raise _Bad("obs_point names a point that point_xyz does not hold")
    if key.size and (key.min() < 0 or np.any(key >= np.diff(off)[image])):
        raise _Bad("obs_keypoint names a keypoint that its image does not have")
    if len(np.unique(image * (int(off[-1]) + 1) + key)) != len(key):
        raise _Bad("a keypoint is observed twice")
    for k in ("obs_point", "obs_image", "obs_keypoint", "keypoints_offset"):
        tracks[k] = tracks[k].astype(np.int64)
    return tracks


def _without_images(tracks: dict[str, np.ndarray], kept: list[bool]) -> dict[str, np.ndarray]:
    """The tracks without the observations of the images not ``kept``; points left without an
    observation go too (the others are numbered anew, in order)."""
    keep_obs = np.asarray(kept)[tracks["obs_image"]]
    out = dict(tracks)
    for k in ("obs_point", "obs_image", "obs_keypoint"):
        out[k] = tracks[k][keep_obs]
    seen = np.bincount(out["obs_point"], minlength=len(tracks["point_xyz"])) > 0
    new_id = np.cumsum(seen) - 1
    out["obs_point"] = new_id[out["obs_point"]]
    for k in ("point_xyz", "point_rgb", "point_error"):
        out[k] = tracks[k][seen]
    return out
