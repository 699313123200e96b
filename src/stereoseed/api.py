"""The Python API in four names, exported at the top level (``import stereoseed``):

* :func:`calibrate`: the stereo pair from photos of a target, or from a pattern's typed points
  (what ``stereoseed calibrate`` does), as a :class:`PairCalibration`;
* :func:`reconstruct`: a sequence into a :class:`Result`, in memory or written to a result folder
  (what ``stereoseed reconstruct`` does);
* :func:`load_result`: a result folder read back as a :class:`Result`;
* :class:`~stereoseed.config.Config`: every setting (``Config.from_toml``, docs/config.md).

The steps underneath are :mod:`stereoseed.pipeline` and :mod:`stereoseed.sfm.mapper` (the
step-by-step API) and :mod:`stereoseed.calibration.rig`.
"""
from __future__ import annotations

import json
import logging
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from stereoseed.calibration.config import CalibrationConfig
from stereoseed.config import Config
from stereoseed.errors import StereoseedError
from stereoseed.io.atomic import write_json
from stereoseed.output import reader
from stereoseed.threads import with_one_blas_thread

__all__ = ["reconstruct", "calibrate", "load_result", "Result", "PairCalibration", "CalibratedCamera", "Config"]

log = logging.getLogger(__name__)

PathLike = str | Path
Progress = Callable[[int, int, str], None]  # (done, total, message), as stereoseed.pipeline calls it


# ------------------------------------------------------------------------------------ results
@dataclass
class Result(reader.Result):
    """A reconstruction: per input image (in order) ``names``, ``sizes`` (width, height) and ``P``
    (3, 4) in the input image's frame, or None where the image was not registered; ``flags``
    (why the run could not vouch for a camera, or None); ``distortion`` (the lens the images were
    undistorted with, or None); ``tracks`` (the points and their observations, tracks.npz's
    arrays, docs/formats.md). ``report``: the run's report (report.json). ``folder``: the result
    folder, None for a run held in memory. Every export takes it
    (:mod:`stereoseed.output.export`)."""

    report: dict[str, Any] | None = None
    _dense: Any = field(default=None, repr=False)  # the DenseCloud of a run in memory, or read once

    @property
    def points(self) -> np.ndarray:
        """The sparse points (P, 3)."""
        return self.tracks["point_xyz"]

    @property
    def dense(self):
        """The quasi-dense cloud (:class:`stereoseed.dense.densify.DenseCloud`: points, colours,
        normals, support), or None when the run had no dense stage; a folder's dense.ply is read
        the first time it is asked for."""
        if self._dense is None and self.folder is not None and (Path(self.folder) / "dense.ply").is_file():
            self._dense = _read_dense(Path(self.folder) / "dense.ply")
        return self._dense

    @property
    def config(self) -> Config | None:
        """The resolved configuration the run used (report.json's "config"): give it to
        :func:`reconstruct` to run again alike."""
        if not self.report or "config" not in self.report:
            return None
        return Config.from_dict(self.report["config"], f"{self.folder or 'the result'}'s report")


def _read_dense(path: Path):
    from stereoseed.dense.densify import DenseCloud
    from stereoseed.io.ply import read_dense_ply

    points, colors, normals, support, _ = read_dense_ply(path)
    return DenseCloud(points, colors, np.zeros_like(points) if normals is None else normals,
                      np.ones(len(points), np.int64) if support is None else support)


def load_result(folder: PathLike) -> Result:
    """A result folder read back (cameras.json, tracks.npz, report.json; dense.ply when asked
    for). Raises :class:`StereoseedError` naming the file that is missing or malformed."""
    base = reader.load_result(folder)
    report = None
    path = Path(folder) / "report.json"
    if path.is_file():
        try:
            report = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:
            raise StereoseedError(f"{path}: not readable JSON ({type(e).__name__}); give a folder written by "
                                  f"stereoseed reconstruct, or run it again") from None
        if not isinstance(report, dict):
            raise StereoseedError(f"{path}: not a run's report (a JSON object); run stereoseed reconstruct again")
    return Result(**{f.name: getattr(base, f.name) for f in fields(reader.Result)}, report=report)


def _in_memory(recon, report: dict[str, Any], cfg: Config, lenses: list, cloud) -> Result:
    """The :class:`Result` that the result folder of ``recon`` would read back as, without writing it."""
    from stereoseed.geometry.lens import lens_index
    from stereoseed.output.results import exported_points, tracks_arrays

    tracks = tracks_arrays(recon, exported_points(recon, cfg.export.far_point_factor))
    views = recon.views
    lens = [lenses[lens_index(i, recon.rig is not None)] if lenses else None for i in range(len(views))]
    return Result(folder=None, names=[v.name for v in views], sizes=[tuple(map(int, v.image_size)) for v in views],
                  P=[v.P_input.copy() if v.registered else None for v in views], tracks=tracks,
                  distortion=[None if L is None else np.asarray(L.distortion, np.float64).copy() for L in lens],
                  distortion_K=[None if L is None else np.asarray(L.K, np.float64).copy() for L in lens],
                  flags=[(v.flag_reason or "flagged") if v.registered and not v.reliable else None for v in views],
                  report=report, _dense=cloud)


# -------------------------------------------------------------------------------- reconstruct
@with_one_blas_thread
def reconstruct(images: PathLike | Sequence[PathLike], calib: PathLike | PairCalibration | Sequence[np.ndarray],
                out: PathLike | None = None, cfg: Config | None = None, *, dense: bool = False, resume: bool = False,
                progress: Progress | None = None, pool=None, dense_progress: Progress | None = None,
                rig_right: PathLike | Sequence[PathLike] | None = None, mesh: bool = False,
                unit: str | None = None) -> Result:
    """Reconstruct an ordered sequence whose first two images are the calibrated pair.

    images: a folder (its images in name order), a text file listing image paths, or a list of
    these, image files and videos (a video stands for its keyframes), as ``stereoseed
    reconstruct`` takes them. calib: a calib.json, a Middlebury ``*_par.txt`` or a COLMAP model
    folder; or a :class:`PairCalibration` (:func:`calibrate`); or the pair's two (3, 4) cameras.
    cfg: the settings (default ``Config()``).

    out None: the run is held in memory and nothing is written (only the descriptors of old
    views go to a temporary folder on long runs, as every run does); the :class:`Result` holds
    the cameras, points, report and, with ``dense``, the quasi-dense cloud. out a folder: the
    whole result folder is written as ``stereoseed reconstruct --out`` writes it (atomically, a
    checkpoint for ``resume``) and read back. progress(done, total, message): after the pair and
    each insertion; pool: where the dense stage's pair jobs run
    (:func:`stereoseed.cluster.executor_for`, default local processes); dense_progress: as each
    dense pair comes in. rig_right: a stereo rig walked with both cameras: ``images`` are the left
    camera's, these the right one's, image k of each taken together (the calibrated pair is the
    first station). mesh: with ``out`` and ``dense``, the dense cloud meshed into ``mesh.ply``
    (the mesh extra). unit: the calibration's unit where it names none (a par file), such as "m".
    Raises :class:`StereoseedError` (one line) for input it cannot use."""
    from stereoseed import pipeline

    cfg = Config() if cfg is None else cfg
    if not isinstance(cfg, Config):
        raise TypeError(f"cfg must be a stereoseed Config, got {type(cfg).__name__}")
    if out is None and mesh:
        raise StereoseedError("a mesh is written into the result folder: give out")
    if out is None and resume:
        raise StereoseedError("resume continues a run written to a folder: give out, the folder of the interrupted run")
    with _calibration_file(calib) as calib_path:
        if out is not None:
            pipeline.reconstruct_to_folder(images, calib_path, out, cfg, dense=dense, resume=resume, progress=progress,
                                           pool=pool, dense_progress=dense_progress, rig_right=rig_right, mesh=mesh,
                                           unit=unit)
            return load_result(out)
        sequence, names, P_pair, lenses = pipeline.load_sequence_and_lenses(images, calib_path, cfg.video,
                                                                            rig_right=rig_right, ordering=cfg.ordering)
        recon, report = pipeline.reconstruct(sequence, names, P_pair, cfg, progress=progress, rig=rig_right is not None)
        from stereoseed.io.files import read_calibration_unit

        report["unit"] = read_calibration_unit(calib_path, unit)  # as a result folder's report.json says it
        cloud = None
        if dense:
            from stereoseed.dense.densify import densify

            cloud, report["dense"] = densify(recon, cfg, None, pool, dense_progress)
        return _in_memory(recon, report, cfg, lenses, cloud)


@contextmanager
def _calibration_file(calib: Any) -> Iterator[str]:
    """The path of ``calib`` (a file or folder as given; a :class:`PairCalibration` or two
    cameras written to a temporary calib.json for the run)."""
    if isinstance(calib, (str, Path)):
        yield str(calib)
        return
    if isinstance(calib, PairCalibration):
        data = calib.report
    else:
        try:
            cameras = [np.asarray(P, np.float64) for P in calib]
        except (TypeError, ValueError):
            raise StereoseedError(f"calib: a calibration file, a PairCalibration or the pair's two 3x4 cameras, got "
                                  f"{type(calib).__name__}") from None
        if len(cameras) != 2 or any(P.shape != (3, 4) for P in cameras):
            raise StereoseedError(f"calib: the pair's two cameras as 3x4 matrices, got shapes "
                                  f"{[P.shape for P in cameras]}")
        data = {"cameras": [{"P": P.tolist()} for P in cameras]}
    with tempfile.TemporaryDirectory(prefix="stereoseed-calib-") as folder:
        yield str(write_json(Path(folder) / "calib.json", data))


# ---------------------------------------------------------------------------------- calibrate
# the note of the target calibrate writes as it found it: what the file is, for whoever opens it (a later
# run knows the file is its own by the record beside it: stereoseed.io.outputs.record_written_file)
REFINED_TARGET_NOTE = "the target's faces where the calibration found them (stereoseed calibrate)"


@dataclass
class CalibratedCamera:
    """One camera of the pair as calib.json holds it: P = K [R | t] (3, 4) for undistorted
    pixels, in the pattern's frame and unit; its lens ``distortion`` (k1, k2, p1, p2, k3) or
    None; the image size (width, height) when known; the pair view's reprojection RMS (px) over
    ``n_points`` points."""

    P: np.ndarray
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    distortion: np.ndarray | None
    image_size: tuple[int, int] | None
    rms_px: float
    n_points: int

    @property
    def centre(self) -> np.ndarray:
        return -self.R.T @ self.t

    def __repr__(self) -> str:  # the figures a reader looks for, not the matrices
        size = "" if self.image_size is None else f" {self.image_size[0]}x{self.image_size[1]}"
        return (f"CalibratedCamera(f={self.K[0, 0]:.1f} px{size}, centre={np.round(self.centre, 4).tolist()}, "
                f"rms={self.rms_px:.3f} px over {self.n_points} points"
                f"{', with a lens' if self.distortion is not None else ''})")

    @classmethod
    def from_entry(cls, entry: dict[str, Any]) -> "CalibratedCamera":
        d = entry.get("distortion")
        size = entry.get("image_size")
        return cls(np.asarray(entry["P"], np.float64), np.asarray(entry["K"], np.float64),
                   np.asarray(entry["R"], np.float64), np.asarray(entry["t"], np.float64),
                   None if d is None else np.asarray(d, np.float64), None if size is None else tuple(size),
                   float(entry["rms_px"]), int(entry["n_points"]))


@dataclass
class PairCalibration:
    """The calibrated pair: its two ``cameras``; ``report``, what calib.json holds (the cameras
    and how they were found: RMS, the views used and skipped, the target's faces, the rig);
    what the user should know (``warnings``) and how the answer was reached where it is not the
    usual way (``notes``). From photos of a target, ``calibration`` holds every view's result,
    the faces where they were found and the rig (:class:`stereoseed.calibration.rig.Calibration`)."""

    cameras: list[CalibratedCamera]
    report: dict[str, Any]
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    calibration: Any = None

    def __repr__(self) -> str:  # print(pair) in a notebook: its figures, not its arrays (issue #49)
        cams = ", ".join(repr(c) for c in self.cameras)
        return f"PairCalibration([{cams}], {len(self.warnings)} warning(s), {len(self.notes)} note(s))"

    def write(self, path: PathLike) -> Path:
        """Write calib.json (atomically) to ``path``: what ``reconstruct --calib`` reads."""
        path = Path(path)
        if path.is_dir():
            raise StereoseedError(f"{path}: is a folder; give the calibration file to write, e.g. calib.json")
        _refuse_non_finite(self.report.get("cameras", []), [f"camera {i}" for i in (1, 2)])
        return write_json(path, self.report)

    def write_target(self, path: PathLike) -> Path:
        """Write the target as the calibration found it (target.json's form; give it with
        ``rigid_target`` to keep it). Only for a calibration from photos of a target."""
        from stereoseed.calibration.target import target_json

        if self.calibration is None:
            raise StereoseedError("write_target: this calibration is from typed points; it found no target")
        path = Path(path)
        return write_json(path, target_json(self.calibration.target, path.parent.resolve(), REFINED_TARGET_NOTE))


@with_one_blas_thread
def calibrate(inputs: Sequence[Any], *, target: PathLike | None = None,
              lens_images: tuple[Sequence[PathLike], Sequence[PathLike]] = ((), ()),
              intrinsics: tuple[Any, Any] = (None, None), rig: bool = False, rigid_target: bool = False,
              k3: bool = False, lens: bool = False, cfg: CalibrationConfig | None = None) -> PairCalibration:
    """Calibrate the stereo pair.

    With ``target`` (a target.json, ``stereoseed target`` or examples/): ``inputs`` are the two
    pair photos (paths); ``lens_images`` more photos of the target per camera (the lens over the
    frame); ``rig``: the pair is fixed and took its i-th lens photos together (one relative pose
    from every shot); ``intrinsics``: per camera, an OpenCV calibration file or (K, distortion)
    known already, or None; ``rigid_target``: keep the faces where target.json puts them.
    Without: the paper's typed points, ``inputs`` = (pattern (N, 3) 'X Y Z', pixels of camera 1
    (N, 2) 'u v', pixels of camera 2), each a text file or an array; ``lens``: estimate the
    distortion too (from one view: right only under the pattern). ``k3``: a third radial term.
    cfg: when a view is dropped and a camera refused (``max_rms_px``). Raises
    :class:`StereoseedError` (one line) when the inputs cannot be used or a camera is no
    physical one."""
    cfg = CalibrationConfig() if cfg is None else cfg
    if target is not None:
        return _from_target(inputs, target, lens_images, intrinsics, rig, rigid_target, k3, cfg)
    if len(inputs) != 3 or any(lens_images) or rig or any(i is not None for i in intrinsics):
        raise StereoseedError("calibrate: give PATTERN POINTS1 POINTS2 (typed points), or --target target.json "
                              "IMAGE1 IMAGE2 (photos of the printed target, with --lens-images1/2)")
    return _from_points(inputs, lens, k3, cfg)


def _points(value: Any, columns: int, what: str) -> tuple[np.ndarray, str]:
    from stereoseed.io.files import read_points_file

    if isinstance(value, (str, Path)):
        return read_points_file(value, columns), str(value)
    a = np.asarray(value, np.float64)
    if a.ndim != 2 or a.shape[1] != columns:
        raise StereoseedError(f"{what}: {columns} numbers per point expected, got an array of shape {a.shape}")
    return a, what


def _from_points(inputs: Sequence[Any], lens: bool, k3: bool, cfg: CalibrationConfig) -> PairCalibration:
    """The paper's form: a pattern and the pixels of its points in each pair image."""
    from stereoseed.calibration.lens_calibration import calibrate_lens
    from stereoseed.estimators.calibration import calibrate_camera

    pattern, pattern_name = _points(inputs[0], 3, "the pattern")
    entries, warnings = [], []
    for i, value in enumerate(inputs[1:], 1):
        pixels, name = _points(value, 2, f"camera {i}'s pixels")
        if len(pixels) != len(pattern):
            raise StereoseedError(f"{name}: {len(pixels)} image points but {len(pattern)} pattern points "
                                  f"in {pattern_name}; give one pixel per pattern point, same order")
        _refuse_degenerate_pixels(pixels, name)
        try:
            if lens:
                cal = calibrate_lens([(pattern, pixels)], k3=k3, what=[name], max_rms_px=cfg.max_rms_px)
                entries.append(cal.to_dict())
                warnings += cal.warnings
            else:
                entries.append(calibrate_camera(pattern, pixels, what=name).to_dict())
        except np.linalg.LinAlgError:  # a pattern of 1e-200 m: its normal equations are singular in floating point
            raise StereoseedError(f"{pattern_name}: its points are too close together to be told apart "
                                  f"numerically (extent {np.ptp(pattern, axis=0).max():.3g}); give them in "
                                  f"millimetres or metres") from None
    names = [str(v) if isinstance(v, (str, Path)) else f"camera {i}'s pixels" for i, v in enumerate(inputs[1:], 1)]
    _refuse_non_finite(entries, names)
    return PairCalibration([CalibratedCamera.from_entry(e) for e in entries], {"cameras": entries}, warnings)


# typed pixels whose spread across their narrowest direction (RMS) is below this lie on one line
# or at one point within a click's error: no camera follows from them (the DLT's solution is then
# a rank-deficient P, NaN after its decomposition)
MIN_PIXEL_SPREAD_PX = 1.0


def _refuse_degenerate_pixels(pixels: np.ndarray, name: str) -> None:
    centred = pixels - pixels.mean(axis=0)
    narrowest = np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(len(pixels))
    if not narrowest >= MIN_PIXEL_SPREAD_PX:
        where = "at one point" if np.ptp(pixels, axis=0).max() < MIN_PIXEL_SPREAD_PX else "on one line"
        raise StereoseedError(f"{name}: the {len(pixels)} pixels lie {where} (spread {narrowest:.3g} px across it); "
                              f"no camera follows from them: give each pattern point's own pixel, in the same order")


def _refuse_non_finite(entries: list[dict[str, Any]], names: list[str]) -> None:
    """Refuse a camera with a NaN or infinite number before anything is written (a camera of NaN
    would be written as a good one, and every later step would fail far from the cause)."""
    for entry, name in zip(entries, names):
        for key in ("P", "K", "R", "t", "rms_px", "distortion"):
            value = entry.get(key)
            if value is not None and not np.all(np.isfinite(np.asarray(value, np.float64))):
                raise StereoseedError(f"{name}: the calibration came out with a non-finite {key} (NaN or infinite); "
                                      f"check that the points are the pattern's, in the same order, and not all "
                                      f"alike")


def _known(value: Any, label: str, size: tuple[int, int] | None):
    """Known (K, distortion) of a camera: from an OpenCV calibration file (its image size
    checked against the photos') or given as a pair of arrays; None: to estimate."""
    from stereoseed.calibration.lens_calibration import read_opencv_camera

    if value is None or (isinstance(value, str) and not value):
        return None
    if not isinstance(value, (str, Path)):
        K, d = value
        return np.asarray(K, np.float64), np.asarray(d, np.float64)
    K, d, file_size = read_opencv_camera(value)
    if file_size is not None and size is not None and tuple(file_size) != tuple(size):
        raise StereoseedError(f"{value}: calibrated for {file_size[0]}x{file_size[1]} images, but {label}'s images "
                              f"are {size[0]}x{size[1]}; give the file of this camera at this resolution")
    return K, d


def _from_target(inputs: Sequence[Any], target_path: PathLike, lens_images: tuple, intrinsics: tuple, rig: bool,
                 rigid_target: bool, k3: bool, cfg: CalibrationConfig) -> PairCalibration:
    """Photos of the target: corners found, the cameras, their lenses, the target's faces (and
    the rig) estimated together."""
    from stereoseed.calibration.detection import detect_target
    from stereoseed.calibration.rig import calibrate_cameras, calibration_json
    from stereoseed.calibration.target import load_target

    if len(inputs) != 2:
        raise StereoseedError("calibrate --target target.json: give the two images of the calibrated pair")
    target = load_target(target_path)
    labels = ["camera 1", "camera 2"]
    lens = [list(lens_images[0] or []), list(lens_images[1] or [])]
    if rig and len(lens[0]) != len(lens[1]):
        raise StereoseedError(f"--rig: {len(lens[0])} photos in --lens-images1 but {len(lens[1])} in --lens-images2; "
                              "the rig's photos go in pairs, taken together, in the same order")
    # the pair's photos may be among the lens photos (all of a rig's shots given): each is used once;
    # a rig's shots stay paired, so a shot holding a pair photo is dropped for both cameras
    same = [[Path(p).resolve() == Path(inputs[c]).resolve() for p in lens[c]] for c in (0, 1)]
    if rig:
        keep = [not (a or b) for a, b in zip(*same)]
        lens = [[p for p, k in zip(lens[c], keep) if k] for c in (0, 1)]
    else:
        lens = [[p for p, dup in zip(lens[c], same[c]) if not dup] for c in (0, 1)]
    detections, known = [], []
    for c in (0, 1):
        # a view that cannot be read is the user's error (one line); one without the target is
        # judged by the calibration (skipped with its reason)
        detections.append([detect_target(p, target, what=str(p)) for p in [inputs[c]] + lens[c]])
        known.append(_known(intrinsics[c], labels[c], detections[-1][0].image_size))
    cal = calibrate_cameras(target, detections, rig=rig, rigid_target=rigid_target, k3=k3, known=known, cfg=cfg,
                            pair=True, leave_one_out=rig, labels=labels)
    data = calibration_json(cal)
    _refuse_non_finite(data["cameras"], labels)
    return PairCalibration([CalibratedCamera.from_entry(e) for e in data["cameras"]], data, list(cal.warnings),
                           list(cal.notes), cal)
