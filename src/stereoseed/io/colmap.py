"""COLMAP's cameras + images (text or binary) read back as calibrated cameras.

Conventions (docs/formats.md): COLMAP's pixel (0, 0) is the top-left *corner* of the top-left
pixel (ours: its centre), so principal points move by -0.5 px; its quaternion (qw, qx, qy, qz)
and t are world-to-camera (ours too).
"""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from stereoseed.errors import StereoseedError
from stereoseed.geometry.projection import compose_projection
from stereoseed.geometry.models import rotation_from_quaternion

__all__ = ["COLMAP_MODELS", "read_colmap_cameras"]

# COLMAP's camera models: name -> (id, number of parameters)
COLMAP_MODELS = {"SIMPLE_PINHOLE": (0, 3), "PINHOLE": (1, 4), "SIMPLE_RADIAL": (2, 4), "RADIAL": (3, 5),
                 "OPENCV": (4, 8), "FULL_OPENCV": (6, 12)}
_MODEL_NAMES = {v[0]: k for k, v in COLMAP_MODELS.items()}


def read_colmap_cameras(folder: str | Path) -> dict[str, np.ndarray]:
    """The cameras of a COLMAP model folder (cameras + images, .txt or .bin) as {image name: P
    (3, 4) in our pixel convention}. Pinhole models only (SIMPLE_PINHOLE, PINHOLE; radial and
    OPENCV models with zero distortion): a lens model is refused with a message."""
    folder = Path(folder)
    if (folder / "cameras.txt").is_file() and (folder / "images.txt").is_file():
        cameras, images = _read_text(folder)
    elif (folder / "cameras.bin").is_file() and (folder / "images.bin").is_file():
        cameras, images = _read_binary(folder)
    else:
        raise StereoseedError(f"{folder}: not a COLMAP model (no cameras.txt + images.txt or cameras.bin + images.bin); "
                              f"give the folder holding them (e.g. sparse/0)")
    out = {}
    for name, (q, t, cam) in images.items():
        if cam not in cameras:
            raise StereoseedError(f"{folder}: image {name!r} refers to camera {cam}, which is not in the model")
        model, params = cameras[cam]
        n = COLMAP_MODELS.get(model, (None, None))[1]
        if n is None or len(params) != n:
            raise StereoseedError(f"{folder}: camera {cam} has model {model} with {len(params)} parameters; "
                                  f"stereoseed reads {', '.join(COLMAP_MODELS)}")
        if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            f, cx, cy = params[:3]
            fx = fy = f
            distortion = params[3:]
        else:
            fx, fy, cx, cy = params[:4]
            distortion = params[4:]
        if any(abs(d) > 0 for d in distortion):
            raise StereoseedError(f"{folder}: camera {cam} ({model}) has lens distortion {list(distortion)}, which "
                                  f"stereoseed does not model yet; undistort the images (colmap image_undistorter)")
        K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
        out[name] = compose_projection(K, rotation_from_quaternion(q), np.asarray(t))
    return out


def _read_text(folder: Path) -> tuple[dict, dict]:
    def lines(name: str) -> list[str]:
        try:
            text = (folder / name).read_text()
        except UnicodeDecodeError:
            raise StereoseedError(f"{folder / name}: not a text file") from None
        return [ln for ln in text.splitlines() if not ln.lstrip().startswith("#")]

    try:
        cameras = {int(r[0]): (r[1], [float(v) for v in r[4:]])
                   for r in (ln.split() for ln in lines("cameras.txt")) if r}
        images = {}
        body = lines("images.txt")
        while body and not body[-1].strip():
            body.pop()
        # two lines per image: the pose, then its 2D points (possibly an empty line)
        for pose in body[0::2]:
            r = pose.split()
            images[" ".join(r[9:])] = ([float(v) for v in r[1:5]], [float(v) for v in r[5:8]], int(r[8]))
    except (ValueError, IndexError):
        raise StereoseedError(f"{folder}: cameras.txt or images.txt is not in COLMAP's text format") from None
    return cameras, images


def _read_binary(folder: Path) -> tuple[dict, dict]:
    try:
        data = (folder / "cameras.bin").read_bytes()
        (n,), pos, cameras = struct.unpack_from("<Q", data), 8, {}
        for _ in range(n):
            cam, model_id, _w, _h = struct.unpack_from("<iiQQ", data, pos)
            pos += 24
            model = _MODEL_NAMES.get(model_id, f"model {model_id}")
            k = COLMAP_MODELS.get(model, (None, 0))[1]
            if model not in COLMAP_MODELS:
                raise StereoseedError(f"{folder}: camera {cam} has a COLMAP model stereoseed does not read ({model})")
            cameras[cam] = (model, list(struct.unpack_from(f"<{k}d", data, pos)))
            pos += 8 * k
        data = (folder / "images.bin").read_bytes()
        (n,), pos, images = struct.unpack_from("<Q", data), 8, {}
        for _ in range(n):
            values = struct.unpack_from("<i7di", data, pos)
            pos += 64
            end = data.index(b"\0", pos)
            name = data[pos:end].decode("utf-8")
            pos = end + 1
            (n2d,) = struct.unpack_from("<Q", data, pos)
            pos += 8 + 24 * n2d
            images[name] = (list(values[1:5]), list(values[5:8]), values[8])
    except (struct.error, ValueError, UnicodeDecodeError):
        raise StereoseedError(f"{folder}: cameras.bin or images.bin is not in COLMAP's binary format") from None
    return cameras, images
