"""A ChArUco cube other than the example's (50 mm, 6 x 6 squares of 7 mm a face, DICT_4X4_250),
assembled with known errors, photographed by a rendered stereo rig through a lens: the ground
truth for the calibration's tests."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from stereoseed.calibration.detection import Detection, detect_target
from stereoseed.calibration.target import Target, load_target
from stereoseed.synthetic.target import from_boards, render_target

SIZE = (640, 480)
K1 = np.array([[1150.0, 0.0, 326.0], [0.0, 1150.0, 236.0], [0.0, 0.0, 1.0]])
K2 = np.array([[1080.0, 0.0, 314.0], [0.0, 1085.0, 244.0], [0.0, 0.0, 1.0]])
LENS1 = np.array([-0.12, 0.25, 0.0008, -0.0005, 0.0])
LENS2 = np.array([0.06, -0.15, -0.0004, 0.0006, 0.0])
# camera 2 from camera 1: 70 mm to the right, turned 12 degrees towards the cube 240 mm ahead
RIG_R = cv2.Rodrigues(np.array([0.0, np.radians(12.0), 0.0]))[0]
RIG_T = -RIG_R @ np.array([70.0, 0.0, 0.0])
# the faces' nominal poses in the cube's frame: the example cube's (examples/charuco-cube)
_ROTATIONS = [(2.22144147, 2.22144147, 0), (-1.57079633, 0, 0), (-1.20919958, -1.20919958, 1.20919958),
              (0, 2.22144147, -2.22144147), (0, 0, 1.57079633), (1.20919958, 1.20919958, 1.20919958)]
_CENTRES = [(-.5, -.5, .5), (-.5, -.5, .5), (.5, -.5, .5), (.5, .5, .5), (.5, -.5, -.5), (-.5, -.5, -.5)]


def write_cube(folder: Path, side: float = 50.0, squares: int = 6, square: float = 7.0) -> Path:
    """target.json of the cube (u, v in mm, no face images), nominal geometry."""
    margin = (side - squares * square) / 2
    faces = []
    for k, (r, c) in enumerate(zip(_ROTATIONS, _CENTRES)):
        R = cv2.Rodrigues(np.array(r, float))[0]
        faces.append({"origin": (R @ [margin, margin, 0.0] + side * np.array(c)).tolist(),
                      "u_axis": R[:, 0].tolist(), "v_axis": R[:, 1].tolist(),
                      "board": {"dictionary": "DICT_4X4_250", "squares": [squares, squares], "square_px": square,
                                "marker_px": 0.75 * square, "first_id": k * squares * squares // 2,
                                "origin_uv": [0.0, 0.0]}})
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "target.json"
    path.write_text(json.dumps({"unit": "mm", "faces": faces}))
    return path


def assembly_errors(seed: int, n_faces: int = 6, mm: float = 0.8, deg: float = 1.0) -> list[tuple]:
    """Where each face really is: face 0 as described (it is the frame), the others moved by
    about ``mm`` and turned by about ``deg``."""
    rng = np.random.default_rng(seed)
    out = [(np.eye(3), np.zeros(3))]
    for _ in range(n_faces - 1):
        out.append((cv2.Rodrigues(rng.normal(0, np.radians(deg) / np.sqrt(3), 3))[0], rng.normal(0, mm / np.sqrt(3), 3)))
    return out


def shot_poses(n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera 1 from cube, the cube turned at random 240 mm ahead, shifted about the frame."""
    rng = np.random.default_rng(seed)
    poses = []
    for _ in range(n):
        R = cv2.Rodrigues(rng.normal(0, 1.6, 3))[0]
        poses.append((R, np.array([rng.uniform(-25, 25), rng.uniform(-18, 18), rng.uniform(225, 255)])))
    return poses


@dataclass
class Rig:
    target: Target
    truth: list[tuple]  # the faces' true poses (R, t) on the nominal geometry
    poses: list[tuple]  # per shot, camera 1's (R, t)
    detections: list[list[Detection]]  # per camera, per shot
    images: list[list[np.ndarray]]


def photograph(folder: Path, n_shots: int = 8, seed: int = 0, noise: float = 1.0) -> Rig:
    """Both cameras photograph the assembled cube in ``n_shots`` poses."""
    target = load_target(write_cube(folder))
    truth = assembly_errors(seed)
    texture = from_boards(target, texels_per_square=28, poses=truth)
    poses = shot_poses(n_shots, seed)
    detections, images = [[], []], [[], []]
    for i, (R, t) in enumerate(poses):
        for c, (K, lens, (Rc, tc)) in enumerate(((K1, LENS1, (R, t)), (K2, LENS2, (RIG_R @ R, RIG_R @ t + RIG_T)))):
            img = render_target(texture, K, Rc, tc, size=SIZE, distortion=lens, supersample=2, noise_sigma=noise,
                                seed=10 * i + c, background=100)
            images[c].append(img)
            detections[c].append(detect_target(img, target, what=f"cam{c}_{i}.png"))
    return Rig(target, truth, poses, detections, images)


def face_error_mm(nominal: Target, found: Target, truth: list[tuple]) -> np.ndarray:
    """Per face, the largest distance (mm) between a corner where ``found`` puts it and where the
    face truly is (``nominal`` moved by ``truth``)."""
    out = []
    for f, g, (R, t) in zip(nominal.faces, found.faces, truth):
        out.append(float(np.linalg.norm(g.corners3d() - (f.corners3d() @ R.T + t), axis=1).max()))
    return np.array(out)
