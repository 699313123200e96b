"""Calibration from real photographs (../shared/data/charucoCube and charucoFlat, pyCamSet's test
data) against OpenCV on the same images: the hand-made cube per camera, the fixed pair from one
shot and from all of them (--rig, also on subsets of the shots against OpenCV's stereoCalibrate with its
own intrinsics), the flat board (`stereoseed intrinsics`).

    python benchmarks/bench_realcal.py          # prints JSON; also a section of make bench
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np

from stereoseed.experiments.paper import shared_data_dir
from stereoseed.calibration.config import CalibrationConfig
from stereoseed.calibration.detection import detect_target
from stereoseed.calibration.intrinsics import plane_coordinates, shared_face_boards
from stereoseed.calibration.rig import calibrate_cameras
from stereoseed.calibration.target import load_target

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _k(K: np.ndarray) -> dict:
    return {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}


def _opencv_faces(target, groups: list[tuple[np.ndarray, np.ndarray]], size) -> dict:
    """OpenCV's calibrateCamera (k1 k2 p1 p2, as ours) with every (face-plane points, pixels)
    group as a board of its own."""
    obj = [np.c_[xy, np.zeros(len(xy))].astype(np.float32) for xy, _ in groups]
    img = [px.astype(np.float32) for _, px in groups]
    rms, K, d, *_ = cv2.calibrateCamera(obj, img, size, None, None, flags=cv2.CALIB_FIX_K3)
    return {"rms_px": float(rms), **_k(K), "distortion": d.ravel().tolist(), "boards": len(obj),
            "corners": int(sum(len(o) for o in obj)), "_K": K, "_d": d.ravel()}


def _opencv_own_detection(target, paths: list[Path], size, min_corners: int = 12) -> dict:
    """OpenCV from its own corners: CharucoDetector per face on each photo (as SOURCE.txt says)."""
    groups = []
    for p in paths:
        grey = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, target.faces[0].board.dictionary))
        markers, marker_ids, _ = cv2.aruco.ArucoDetector(dictionary).detectMarkers(grey)  # once, for every face
        marker_ids = np.empty(0, int) if marker_ids is None else marker_ids.ravel()
        for f in target.faces:
            mine = np.flatnonzero((marker_ids >= f.board.first_id) & (marker_ids < f.board.first_id + f.board.n_markers))
            if len(mine) < 2:
                continue
            corners, ids, _, _ = cv2.aruco.CharucoDetector(f.board.cv_board()).detectBoard(
                grey, markerCorners=tuple(markers[i] for i in mine), markerIds=marker_ids[mine].reshape(-1, 1))
            if ids is not None and len(ids) >= min_corners:
                xy = plane_coordinates(f, f.to_3d(f.board.corner_uv(ids.ravel())))
                groups.append((xy, corners.reshape(-1, 2)))
    return _opencv_faces(target, groups, size)


def _groups(target, detections, min_corners: int = 12) -> list:
    out = []
    for d in detections:
        for f in np.unique(d.face):
            m = d.face == f
            if m.sum() >= min_corners:
                out.append((plane_coordinates(target.faces[f], d.points3d[m]), d.pixels[m]))
    return out


def _camera(cam, reference: dict) -> dict:
    out = {"rms_px": cam.rms_px, "corners": cam.n_points, **_k(cam.K), "distortion": cam.lens.tolist(),
           "views_used": sum(v.used for v in cam.views),
           "skipped": {Path(v.name).name: v.reason for v in cam.views if not v.used},
           "intrinsics_from_faces_one_by_one": cam.from_faces,
           "rigid_target_chi2": None if cam.consistency is None else list(cam.consistency)}
    out["f_vs_opencv_pct"] = [100 * (cam.K[0, 0] / reference["fx"] - 1), 100 * (cam.K[1, 1] / reference["fy"] - 1)]
    out["principal_point_vs_opencv_px"] = float(np.hypot(cam.K[0, 2] - reference["cx"], cam.K[1, 2] - reference["cy"]))
    return out


def _relative(cal, i: int) -> dict:
    v0, v1 = cal.cameras[0].views[i], cal.cameras[1].views[i]
    R = v1.R @ v0.R.T
    t = v1.t - R @ v0.t
    return {"baseline_mm": float(np.linalg.norm(t)), "angle_deg": float(np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0]))),
            "t": t.tolist(), "R": R.tolist(), "faces": [v0.detection.faces_found, v1.detection.faces_found]}


def _pose_difference(a: dict, b: dict) -> dict:
    Ra, Rb = np.array(a["R"]), np.array(b["R"])
    return {"baseline_mm": abs(a["baseline_mm"] - b["baseline_mm"]),
            "translation_mm": float(np.linalg.norm(np.array(a["t"]) - b["t"])),
            "rotation_deg": float(np.degrees(np.linalg.norm(cv2.Rodrigues(Ra @ Rb.T)[0])))}


def cube(folder: Path) -> dict:
    target = load_target(EXAMPLES / "charuco-cube" / "target.json")
    paths = [[folder / f"cam{c}" / f"{i}.jpg" for i in range(24)] for c in (0, 1)]
    start = time.perf_counter()
    detections = [[detect_target(p, target) for p in ps] for ps in paths]
    out: dict = {"detect_seconds_per_image": (time.perf_counter() - start) / 48}
    # each camera on its own, its 24 views (stereoseed intrinsics)
    for c in (0, 1):
        size = detections[c][0].image_size
        own = _opencv_own_detection(target, paths[c], size)
        same = _opencv_faces(target, _groups(target, detections[c]), size)
        start = time.perf_counter()
        cal = calibrate_cameras(target, [detections[c]], pair=False)
        seconds = time.perf_counter() - start
        whole = calibrate_cameras(target, [detections[c]], pair=False, cfg=CalibrationConfig(consistency_quantile=None))
        rigid = calibrate_cameras(target, [detections[c]], pair=False, rigid_target=True)
        out[f"cam{c}"] = {
            "stereoseed": {**_camera(cal.cameras[0], own), "seconds": seconds,
                           "faces_moved": [None if m is None else {"mm": m[0], "deg": m[1]} for m in cal.face_moves]},
            "stereoseed_whole_model_intrinsics": _camera(whole.cameras[0], own),
            "stereoseed_rigid_nominal_target": _camera(rigid.cameras[0], own),
            "opencv_faces_own_corners": {k: v for k, v in own.items() if not k.startswith("_")},
            "opencv_faces_our_corners": {k: v for k, v in same.items() if not k.startswith("_")}}
    # the pair from one shot (each camera's 24 views as lens views), from two different shots
    pair_runs = {}
    for shot in (7, 9):
        dets = [[d[shot]] + [x for i, x in enumerate(d) if i != shot] for d in detections]
        cal = calibrate_cameras(target, dets, labels=["camera 1", "camera 2"])
        pair_runs[shot] = {**_relative(cal, 0), "rms_px": [cam.rms_px for cam in cal.cameras]}
    pair = {f"shot{k}": {k2: v for k2, v in r.items() if k2 not in ("R", "t")} for k, r in pair_runs.items()}
    pair["shot7_vs_shot9"] = _pose_difference(pair_runs[7], pair_runs[9])
    # every shot as the pair's, from one calibration: the spread over shots showing two faces or more to both
    cal = calibrate_cameras(target, detections, pair=False)
    every = [_relative(cal, i) for i in range(24)]
    multi = [r for r in every if len(r["faces"][0]) > 1 and len(r["faces"][1]) > 1]
    pair["every_shot_baseline_mm"] = [round(r["baseline_mm"], 2) for r in every]
    pair["every_shot_angle_deg"] = [round(r["angle_deg"], 3) for r in every]
    pair["shots_with_two_faces_each"] = len(multi)
    pair["their_baseline_range_mm"] = float(np.ptp([r["baseline_mm"] for r in multi]))
    pair["their_angle_range_deg"] = float(np.ptp([r["angle_deg"] for r in multi]))
    out["pair_from_one_shot"] = pair
    # the fixed rig from all 24 shots, against OpenCV's stereoCalibrate on the faces both saw
    start = time.perf_counter()
    rig = calibrate_cameras(target, detections, rig=True)
    seconds = time.perf_counter() - start
    obj, img1, img2 = shared_face_boards(target, detections)
    c0, c1 = rig.cameras
    rms, *_, R, T, _, _ = cv2.stereoCalibrate(obj, img1, img2, c0.K, c0.lens, c1.K, c1.lens, c0.image_size,
                                              flags=cv2.CALIB_FIX_INTRINSIC)
    out["rig_24_shots"] = {
        "baseline_mm": rig.rig.baseline_mm, "angle_deg": rig.rig.angle_deg, "rms_px": [c0.rms_px, c1.rms_px],
        "leave_one_out_mm": rig.rig.spread_mm, "leave_one_out_deg": rig.rig.spread_deg, "seconds": seconds,
        "opencv_stereo_same_intrinsics": {"baseline_mm": float(np.linalg.norm(T)), "rms_px": float(rms),
                                          "angle_deg": float(np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0]))),
                                          "difference_mm": float(np.linalg.norm(rig.rig.t - T.ravel())),
                                          "difference_deg": float(np.degrees(np.linalg.norm(
                                              cv2.Rodrigues(rig.rig.R @ R.T)[0])))}}
    out["rig_24_shots"].update(uncertainty_mm=rig.rig.uncertainty_mm, uncertainty_deg=rig.rig.uncertainty_deg)
    out["rig_subsets"] = rig_subsets(target, detections)
    return out


# the subsets of the 24 shots the rig is tried on (#52): all, halves, fewer shots (fewer lens
# views), views of one face only for at least one camera
RIG_SUBSETS = {"all24": list(range(24)), "even12": list(range(0, 24, 2)), "odd12": list(range(1, 24, 2)),
               "first8": list(range(8)), "mid8": list(range(6, 14)), "last10": list(range(14, 24)),
               "every3": list(range(0, 24, 3)), "odd6": list(range(1, 24, 4)), "six": [0, 5, 9, 12, 16, 21],
               "one_face": [2, 3, 4, 11, 12, 13, 18, 19, 20, 21]}


def _opencv_rig(target, detections) -> tuple[np.ndarray, np.ndarray]:
    """stereoCalibrate on the faces both cameras saw, the intrinsics held at OpenCV's per-face fits."""
    size = detections[0][0].image_size
    cams = [_opencv_faces(target, _groups(target, detections[c]), size) for c in (0, 1)]
    obj, img1, img2 = shared_face_boards(target, detections)
    *_, R, T, _, _ = cv2.stereoCalibrate(obj, img1, img2, cams[0]["_K"], cams[0]["_d"], cams[1]["_K"], cams[1]["_d"],
                                         size, flags=cv2.CALIB_FIX_INTRINSIC)
    return R, T.ravel()


def rig_subsets(target, detections) -> dict:
    """--rig against OpenCV's stereoCalibrate (intrinsics at its per-face fits) on the same shots:
    the rotation and translation apart, the stated uncertainty, and whether it warned of weak
    intrinsics; and against OpenCV on all 24 shots (the best estimate there is)."""
    R_all, T_all = _opencv_rig(target, detections)
    out = {}
    for name, shots in RIG_SUBSETS.items():
        dets = [[d[i] for i in shots] for d in detections]
        R, T = _opencv_rig(target, dets)
        start = time.perf_counter()
        cal = calibrate_cameras(target, dets, rig=True)
        rig = cal.rig
        apart = {k: {"rotation_deg": float(np.degrees(np.linalg.norm(cv2.Rodrigues(rig.R @ Rr.T)[0]))),
                     "translation_mm": float(np.linalg.norm(rig.t - Tr)),
                     "baseline_mm": float(rig.baseline_mm - np.linalg.norm(Tr))}
                 for k, (Rr, Tr) in (("opencv_same_shots", (R, T)), ("opencv_all_24", (R_all, T_all)))}
        out[name] = {"shots": shots, "baseline_mm": rig.baseline_mm, "angle_deg": rig.angle_deg,
                     "opencv_baseline_mm": float(np.linalg.norm(T)),
                     "opencv_angle_deg": float(np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0]))), **apart,
                     "uncertainty_mm": rig.uncertainty_mm, "uncertainty_deg": rig.uncertainty_deg,
                     "leave_one_out_mm": rig.spread_mm, "leave_one_out_deg": rig.spread_deg,
                     "covers_opencv": bool(apart["opencv_same_shots"]["rotation_deg"] <= rig.uncertainty_deg
                                           and apart["opencv_same_shots"]["translation_mm"] <= rig.uncertainty_mm),
                     "warns_weak_intrinsics": any("weakly determined" in w for w in cal.warnings),
                     "pull_deg": rig.trade[0]["rig_turns_deg"] if rig.trade else None,
                     "checks": rig.checks, "seconds": time.perf_counter() - start}
    return out


def flat(folder: Path) -> dict:
    target = load_target(EXAMPLES / "charuco-flat" / "target.json")
    paths = [folder / f"cal{i}.jpg" for i in range(1, 23)]
    detections = [detect_target(p, target) for p in paths]
    start = time.perf_counter()
    cal = calibrate_cameras(target, [detections], pair=False)
    seconds = time.perf_counter() - start
    cam = cal.cameras[0]
    used = [v.detection for v in cam.views if v.used]
    size = cam.image_size
    same = _opencv_faces(target, _groups(target, used, min_corners=4), size)
    own = _opencv_own_detection(target, paths, size, min_corners=6)
    return {"stereoseed": {**_camera(cam, same), "seconds": seconds,
                           "rms_over_opencv_same_corners": cam.rms_px / same["rms_px"],
                           "cal13_corners": len(detections[12]), "cal13_left_at_opencv": sum(detections[12].unrefined)},
            "opencv_same_corners": {k: v for k, v in same.items() if not k.startswith("_")},
            "opencv_own_corners_every_view": {k: v for k, v in own.items() if not k.startswith("_")}}


def run() -> dict:
    data = shared_data_dir()  # $STEREOSEED_DATA, else ../shared/data
    out: dict = {}
    for name, bench in (("charucoCube", cube), ("charucoFlat", flat)):
        folder = data / name
        out[name] = bench(folder) if folder.is_dir() else {"skipped": f"{folder} not found (set STEREOSEED_DATA)"}
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=1))
