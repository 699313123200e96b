"""A result folder read back (cameras.json, tracks.npz) as a :class:`Result`: the input of the
exports (:mod:`stereoseed.output.export`)."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stereoseed.errors import StereoseedError
from stereoseed.output.results import FORMAT_VERSION

__all__ = ["Result", "load_result"]


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

    @property
    def registered(self) -> list[int]:
        return [i for i, P in enumerate(self.P) if P is not None]

    def keypoints(self, image: int) -> np.ndarray:
        """(K, 2) keypoints of image ``image`` (our pixel convention), indexed by obs_keypoint."""
        off = self.tracks["keypoints_offset"]
        return self.tracks["keypoints_xy"][off[image]:off[image + 1]]


def load_result(folder: str | Path) -> Result:
    """Read cameras.json and tracks.npz of a result folder. Raises :class:`StereoseedError`
    naming the missing or unreadable file."""
    folder = Path(folder)
    cams_path, tracks_path = folder / "cameras.json", folder / "tracks.npz"
    for p in (cams_path, tracks_path):
        if not p.is_file():
            raise StereoseedError(f"{folder}: no {p.name}; give a folder written by stereoseed reconstruct "
                                  f"(version {FORMAT_VERSION} or later)")
    try:
        cams = json.loads(cams_path.read_text())
        images = cams["images"]
        with np.load(tracks_path) as npz:
            tracks = {k: npz[k] for k in npz.files}
        names = [im["name"] for im in images]
        sizes = [(int(im["width"]), int(im["height"])) for im in images]
        Ps = [np.asarray(im["P"], np.float64) if im.get("registered") else None for im in images]
        lens = [np.asarray(im["distortion"], np.float64) if "distortion" in im else None for im in images]
    except (ValueError, KeyError, TypeError, OSError) as e:
        raise StereoseedError(f"{folder}: cameras.json or tracks.npz is not as stereoseed writes it ({e})") from None
    return Result(folder, names, sizes, Ps, tracks, lens)
