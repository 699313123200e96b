"""A rendered scene written as a user's folder, for the tests that run commands on files."""
from __future__ import annotations

from pathlib import Path

from stereoseed.io.files import write_json
from stereoseed.synthetic.scene import SyntheticScene, write_scene


def scene_on_disk(scene: SyntheticScene, folder: Path, images: Path | None = None) -> tuple[dict, Path]:
    """The scene's images and images.txt (:func:`write_scene`, into ``images``, default
    ``folder``) and ``folder``/calib.json holding its true pair. Returns (write_scene's paths,
    the calib.json path)."""
    paths = write_scene(scene, folder if images is None else images)
    return paths, write_calib(Path(folder) / "calib.json", scene.P[:2])


def write_calib(path: Path, Ps) -> Path:
    """A calib.json at ``path`` holding the cameras Ps (each (3, 4)), the pair first."""
    write_json(path, {"cameras": [{"P": P.tolist()} for P in Ps]})
    return path


def write_video(path: Path, images: list) -> Path:
    """The images (H, W, 3) uint8 as an MJPG video at 25 frames a second."""
    import cv2

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, images[0].shape[1::-1])
    for image in images:
        writer.write(image)
    writer.release()
    return path
