"""The whole run over an ordered sequence: load it, reconstruct it with the incremental mapper
(:mod:`stereoseed.sfm.mapper`), save the results (:func:`reconstruct_to_folder` does all three, as
``stereoseed reconstruct`` and each job of ``stereoseed batch``). The step-by-step API is the
mapper's.
"""
from __future__ import annotations

import errno
import logging
import os
import shutil
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, Sequence

import numpy as np

from stereoseed.scene.view_store import release_pixels, working_set
from stereoseed.scene.checkpoint import SPILL_SUFFIX, CheckpointWriter, inputs_key, load_checkpoint, spill_folder
from stereoseed.config import Config
from stereoseed.io.config import VideoConfig
from stereoseed.sfm.correspondence import CorrespondenceSource, HarrisZncc, Prefetching
from stereoseed.errors import StereoseedError
from stereoseed.io.files import (IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, check_image_name, list_images, read_calibration,
                                 read_calibration_unit, read_image)
from stereoseed.geometry.lens import lens_index, undistort_image, undistortion_maps
from stereoseed.calibration.lens_calibration import read_lenses
from stereoseed.sfm.mapper import finish, initialise, pair_rig
from stereoseed.sfm.steps import frame_offset, insert_next, shift
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.io.sequence import ImageSequence, header_size
from stereoseed.matching.alignment import release_gradients
from stereoseed.matching.ordering import OrderingConfig, thumbnail, too_many_to_order, walk_order
from stereoseed.io.video import read_keyframes, read_rig_keyframes
from stereoseed.output.inputs import write_inputs
from stereoseed.output.report.html import write_report_html
from stereoseed.output.result_set import ResultSet
from stereoseed.output.results import write_result

if TYPE_CHECKING:  # a type only: the executors' module is not needed to run
    from stereoseed.cluster import JobPool

__all__ = ["reconstruct", "as_finished", "load_sequence", "load_sequence_and_lenses", "save_outputs", "reconstruct_to_folder", "CHECKPOINT"]

log = logging.getLogger(__name__)

# progress(done, total, message): called after the pair and after each insertion
Progress = Callable[[int, int, str], None]
# after_insertion(recon, per_image): likewise, with the model as it stands (see reconstruct)
AfterInsertion = Callable[[Reconstruction, list[dict[str, Any]]], None]

CHECKPOINT = ".checkpoint.npz"  # in the staging folder, kept after an interruption for resume


def reconstruct(images: list[np.ndarray], names: list[str], P_pair: list[np.ndarray], cfg: Config = Config(),
                progress: Progress | None = None, source: CorrespondenceSource | None = None,
                checkpoint: str | Path | None = None, resume: bool = False,
                after_insertion: AfterInsertion | None = None, rig: bool = False) -> tuple[Reconstruction, dict[str, Any]]:
    """The incremental loop over an ordered sequence whose first two images are the calibrated
    pair (P_pair: their two (3, 4) cameras). An image that cannot be placed is reported and
    skipped; the next one is placed from the last registered images. Returns the
    reconstruction and a JSON-able report (per image, the final step, the resolved config).

    checkpoint: a file rewritten after the pair and after each insertion (:mod:`stereoseed.scene.checkpoint`);
    resume: continue from it when it was written for these inputs and settings (the result is
    the uninterrupted run's; the report lists the images that were resumed).
    after_insertion: called after the pair and after each insertion this run performs (not those
    a resumed run takes from its checkpoint) with the model and the per-image reports so far; it
    must leave both as it found them (:func:`as_finished` gives
    what a run on the images so far would return, without disturbing this one).
    rig: the images are a stereo rig's stations, left and right interleaved (:func:`load_sequence`'s
    ``rig_right``; the pair is the first station)."""
    t0 = time.perf_counter()
    n = len(images)
    if n < 2:
        raise StereoseedError("a sequence needs at least the two images of the calibrated pair")
    cfg = cfg.resolve()
    options = cfg.mapper_options()  # each of the mapper's components is handed its own sections
    key = inputs_key(images, names, P_pair, cfg, rig) if checkpoint is not None else ""
    # a world frame far from the cameras (UTM-sized coordinates) is moved next to them for the
    # run and put back at the end: float64 keeps ~16 digits, and 1e7 m of offset leaves a BA
    # centimetres of resolution
    offset = frame_offset(P_pair)
    if offset is not None:
        P_pair = [np.asarray(P, np.float64) @ shift(offset) for P in P_pair]
        log.info("world frame %s from the pair's cameras: the run works %s nearer", offset.tolist(), offset.tolist())
    source = source or HarrisZncc.of(options)
    state = None
    if checkpoint is not None and resume:
        state = load_checkpoint(checkpoint, images, names, key)
    if checkpoint is not None and state is None:
        _forget_checkpoint(checkpoint)  # another run's, or unusable: nothing of it outlives this start
    # The background threads start with the run: the pair's second image and the next ones are
    # read and given their interest points while this thread does the first image, then the pair
    # (the calibrated pair's matching and triangulation left the second core idle).
    first_prefetched = len(state[1]) if state is not None else 1
    # checkpoints are written while the run goes on; leaving waits for the last one
    with CheckpointWriter(checkpoint, key) as saver, \
            Prefetching(source, _prefetched_image(images), n, first=first_prefetched) as prefetching:
        if state is not None:
            recon, per_image = state
            recon.rig = pair_rig(P_pair, rig)
            for i in working_set(recon, cfg):  # the next insertions read their grey images
                recon.views[i].restore_gray()
            log.info("resuming after %s (%d of %d images done)", names[len(per_image) - 1], len(per_image), n)
        else:
            recon, _ = initialise(images, names, P_pair, options, prefetching, rig=rig)
            per_image = recon.reports()
            saver.save(recon)
            if after_insertion:
                after_insertion(recon, per_image)
        resumed = [r["image"] for r in per_image] if state is not None else []
        if progress:
            progress(len(per_image), n, f"pair: {per_image[1].get('new_points', 0)} points")
        # descriptors of old views go to files: beside the checkpoint, which then names them instead
        # of copying them, else in a temporary folder removed when the run returns (a memory map of
        # a file keeps working once the folder is removed on POSIX systems)
        _allow_open_files(n + 256)  # every spilled view's memory map holds a file descriptor
        if checkpoint is not None:
            spill = spill_folder(checkpoint)
            spill.mkdir(mode=0o700, parents=True, exist_ok=True)  # the checkpoint names what is in it
        else:
            spill_holder = tempfile.TemporaryDirectory(prefix="stereoseed-spill-", ignore_cleanup_errors=True)
            spill = Path(spill_holder.name)
        for k in range(len(per_image), n):
            rep = insert_next(recon, images, k, options, prefetching, spill, saver)
            if progress:
                progress(k + 1, n, f"{names[k]}: {rep['status']}")
            if after_insertion:  # the reports so far, rendered only for whoever reads them
                after_insertion(recon, recon.reports())
    report = _finished(recon, cfg, t0, source)
    # the sparse run is over: no more alignment, and no grey image is read again (a later reader
    # computes it again from the image); at 24 megapixels the views' were 100 MB each
    release_gradients()
    for view in recon.views:
        release_pixels(view)
    if offset is not None:
        for v in recon.registered_views:
            recon.views[v].P = recon.views[v].P @ shift(-offset)
        recon.points[:] += offset
        report["frame_offset"] = offset.tolist()
    if resumed:
        report["resumed_images"] = resumed
    log.info("registered %d/%d images, %d points", report["registered"], n, report["points"])
    return recon, report


def _forget_checkpoint(checkpoint: str | Path) -> None:
    """Remove a checkpoint and its spill folder (this run writes its own)."""
    Path(checkpoint).unlink(missing_ok=True)
    spill = spill_folder(checkpoint)
    if spill.is_dir() and not spill.is_symlink():
        shutil.rmtree(spill)
    else:
        spill.unlink(missing_ok=True)


class _NotRead(Exception):
    """An image the sequence does not decode (:meth:`ImageSequence.withheld`) or cannot
    (:meth:`ImageSequence.unreadable`)."""


def _prefetched_image(images: Sequence[np.ndarray]) -> Callable[[int], np.ndarray]:
    """What the prefetching thread reads: an image the sequence withholds for its size, or
    cannot decode, is not worked on ahead (the mapper refuses it by its size alone, the loop
    skips it by its reason)."""
    if not isinstance(images, ImageSequence):
        return images.__getitem__

    def image_of(i: int) -> np.ndarray:
        if images.withheld(i):
            raise _NotRead(i)
        image = images[i]
        if images.unreadable(i):
            raise _NotRead(i)
        return image

    return image_of


def _finished(recon: Reconstruction, cfg: Config, t0: float, source: CorrespondenceSource | None = None) -> dict[str, Any]:
    """The finishing step (:func:`stereoseed.sfm.finishing.finish`) on ``recon``, and the run's
    report (``per_image`` rendered from the views' histories: a view the finishing step registered
    again or could not keep says so)."""
    final = finish(recon, cfg.mapper_options(), source)
    per_image = recon.reports()
    pc = cfg.pipeline
    return {
        "mode": pc.mode, "camera_model": pc.camera_model, "window": pc.window, "ba": pc.ba,
        "images": len(per_image), "registered": len(recon.registered_views),
        "points": int(len(recon.live_points()[0])), "reprojection": recon.reprojection_summary(),
        "per_image": per_image, "final": final, "seconds": time.perf_counter() - t0,
        "config": cfg.to_dict(),
    }


@contextmanager
def as_finished(recon: Reconstruction, cfg: Config,
                source: CorrespondenceSource | None = None) -> Iterator[tuple[Reconstruction, dict[str, Any]]]:
    """Inside an ``after_insertion`` call: (the model, the report) that :func:`reconstruct`
    would return for the images so far, for the block's duration: the finishing step runs on
    the model itself, which is then put back as it was (points, observations, views; arrays
    read in the block are overwritten: copy what you keep) and the run goes on. The
    incremental loop never looks ahead, so this is a run on the images it has reached,
    without running them again (the report's "seconds": the finishing step's)."""
    state = recon.checkpoint()
    try:
        yield recon, _finished(recon, cfg.resolve(), time.perf_counter(), source)
    finally:
        recon.restore(state)


def _allow_open_files(count: int) -> None:
    """Raise this process's soft limit of open files to ``count`` where the hard limit allows (a
    memory map keeps its file open; many systems start processes at 1024, too few for a
    thousand-image run)."""
    try:
        import resource
    except ImportError:  # not POSIX: no such limit to raise
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= count:
        return
    wanted = count if hard == resource.RLIM_INFINITY else min(count, hard)
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (wanted, hard))
    except (ValueError, OSError) as e:
        log.warning("cannot raise the open-file limit to %d (%s): a long run may fail to spill", count, e)
        return
    if wanted < count:
        log.warning("the open-file limit is %d; a run of this length may need %d", wanted, count)


def load_sequence(images_source: str | list[str], calib_path: str, video: VideoConfig = VideoConfig(),
                  keyframes_to: str | Path | None = None, rig_right: str | list[str] | None = None,
                  ordering: OrderingConfig | None = None) -> tuple[ImageSequence, list[str], list[np.ndarray]]:
    """An image sequence and the pair's calibration: (the images, read when needed as uint8 BGR
    (:class:`stereoseed.io.sequence.ImageSequence`), names, the pair's two (3, 4) cameras); as
    :func:`load_sequence_and_lenses`, without the lenses."""
    return load_sequence_and_lenses(images_source, calib_path, video, keyframes_to, rig_right, ordering)[:3]


def _in_walk_order(entries: list[Any], names: list[str], ordering: OrderingConfig,
                   from_folder: bool) -> tuple[list[Any], list[str]]:
    """``entries`` and ``names`` in the walk order their images support
    (:func:`stereoseed.matching.ordering.walk_order`), the calibrated pair first, for a folder's
    photos (any input's with ``OrderingConfig.mode`` "images"); as given for a video's keyframes
    (ordered in time), or when an image's header does not give the second camera's size (it is
    skipped in place, unread) or an image cannot be read (its reason comes when the run reaches it)."""
    if (ordering.mode == "as-given" or (ordering.mode == "auto" and not from_folder) or len(entries) <= 3
            or not all(isinstance(e, Path) for e in entries)):
        return entries, names
    if too_many_to_order(len(entries), ordering):  # (before any thumbnail is read)
        return entries, names
    size = header_size(entries[1])
    if size is None or any(header_size(e) != size for e in entries[2:]):
        log.info("the images are not all of the second camera's size: kept in the order given")
        return entries, names
    try:
        thumbnails = [thumbnail(read_image(e), ordering.thumbnail_px) for e in entries]
    except StereoseedError as e:
        log.info("kept in the order given (%s)", e)
        return entries, names
    order, why, doubt = walk_order(thumbnails, ordering)
    if doubt:
        log.warning("%s", doubt)
    if why is None:
        return entries, names
    log.warning("the images are run in the order their overlaps give (%s): %s", why,
                ", ".join(names[i] for i in order))
    return [entries[i] for i in order], [names[i] for i in order]


def load_sequence_and_lenses(images_source: str | list[str], calib_path: str, video: VideoConfig = VideoConfig(),
                             keyframes_to: str | Path | None = None, rig_right: str | list[str] | None = None,
                             ordering: OrderingConfig | None = None
                             ) -> tuple[ImageSequence, list[str], list[np.ndarray], list]:
    """An image sequence and the pair's calibration: (the images, read when needed as uint8 BGR
    (:class:`stereoseed.io.sequence.ImageSequence`), names, the pair's two (3, 4) cameras, the
    calibration's two lenses (:func:`stereoseed.calibration.lens_calibration.read_lenses`), read
    once for the undistortion and the outputs).

    ``images_source``: a folder (its images in name order), a list file, or several of these and
    image files in order; a video (given directly or listed) stands for its keyframes
    (:func:`stereoseed.io.video.read_keyframes`, named ``VIDEO_FRAME.png``): the two calibrated
    photos first, then the video of the walk; with ``keyframes_to`` (a folder) the keyframes are
    written there as they are chosen and read back when needed. When the calibration carries a lens (calib.json
    "distortion"), every image is undistorted as it is read (one remap; image 0 through the
    first camera's lens, every later image through the second camera's: the moving camera
    keeps its lens, so a zoom that changes the distortion is not modelled), and the cameras hold
    for the undistorted pixels. The first two images are read here: a bad pair is refused
    before any work.

    ``rig_right``: a stereo rig walked with both cameras (:mod:`stereoseed.sfm.rig`):
    ``images_source`` holds the left camera's images, this the right one's, image k of each taken
    together, the first two the calibrated pair; the sequence interleaves them (left, right, ...)
    and each image goes through its own camera's lens.

    ``ordering``: photos in any order are put in walk order from their overlaps
    (:func:`_in_walk_order`; the first two stay the calibrated pair); None: the order given (a
    video's, a rig's always)."""
    sources = [images_source] if isinstance(images_source, (str, Path)) else list(images_source)
    if rig_right is None:
        entries, names = _sequence_entries(sources, video, keyframes_to)
        if ordering is not None:
            from_folder = len(sources) == 1 and Path(sources[0]).is_dir()
            entries, names = _in_walk_order(entries, names, ordering, from_folder)
    else:
        entries, names = _rig_entries(sources, [rig_right] if isinstance(rig_right, (str, Path)) else list(rig_right),
                                      video, keyframes_to)
    if len(entries) < 2:
        raise StereoseedError(f"{' '.join(map(str, sources))}: {len(entries)} image(s); the calibrated pair needs two")
    rig = rig_right is not None
    paths = [e if isinstance(e, Path) else Path(n) for e, n in zip(entries, names)]
    P_pair = read_calibration(calib_path, names)
    lenses = read_lenses(calib_path)
    maps: dict[int, Any] = {}

    def undistort(i: int, image: np.ndarray) -> np.ndarray:
        lens = lenses[lens_index(i, rig)]
        if lens is None:
            return image
        size = image.shape[1::-1]
        if lens.image_size is not None and tuple(size) != tuple(lens.image_size):
            if i >= 2:  # an image of the walk of another size: the mapper skips it, saying why
                return image
            raise StereoseedError(f"{paths[i]}: {size[0]}x{size[1]} pixels, but the calibration's lens is for "
                                  f"{lens.image_size[0]}x{lens.image_size[1]} images; give images of that size")
        if lens_index(i, rig) not in maps:
            maps[lens_index(i, rig)] = undistortion_maps(lens.K, lens.distortion, size)
        return undistort_image(image, lens.K, lens.distortion, maps[lens_index(i, rig)])

    lens_key = repr([None if lens is None else (lens.K.tobytes(), lens.distortion.tobytes(), lens.image_size)
                     for lens in lenses]).encode()  # the undistortion decides the pixels the run sees
    images = ImageSequence(entries, undistort, transform_key=lens_key)
    images[0]  # noqa: B018 - read now: an unreadable pair image fails before any work
    images.skip_unreadable(first=2)  # an unreadable image of the walk is skipped with its reason
    # an image of the walk of another size than the second camera's is skipped by the mapper:
    # its header says so, it is not decoded (a 48-megapixel photo costs seconds and gigabytes)
    if rig_right is None:
        images.withhold_other_sizes(images[1].shape[1::-1], first=2)
    elif images[0].shape != images[1].shape:  # the registrar compares each image with its own side's
        log.info("rig: left images %s, right images %s", images[0].shape[1::-1], images[1].shape[1::-1])
    return images, names, P_pair, lenses


def _rig_entries(left: list, right: list, video: VideoConfig = VideoConfig(),
                 keyframes_to: str | Path | None = None) -> tuple[list, list[str]]:
    """The paths of a rig's two image sources interleaved (left, right, left, ...) and their
    names; names the two sides share get their folder's name in front (cam0_0001.png). Two
    videos (one per side, filmed together) stand for their keyframes, chosen on the left one,
    their first frames the first station (:func:`stereoseed.io.video.read_rig_keyframes`)."""
    is_video = [len(side) == 1 and Path(side[0]).suffix.lower() in VIDEO_EXTENSIONS for side in (left, right)]
    if all(is_video):
        lefts, rights = read_rig_keyframes(left[0], right[0], video, keyframes_to)
        return ([k.entry for pair in zip(lefts, rights) for k in pair],
                [k.name for pair in zip(lefts, rights) for k in pair])
    sides = []
    for sources in (left, right):
        paths: list[Path] = []
        for source in map(Path, sources):
            if source.suffix.lower() in VIDEO_EXTENSIONS:
                raise StereoseedError(f"{source}: --rig takes two folders or lists of images, or two videos (one for "
                                      f"each camera), not a video beside images")
            paths.extend([source] if source.is_file() and source.suffix.lower() in IMAGE_EXTENSIONS
                         else list_images(source))
        for path in paths:
            check_image_name(path, path)
        sides.append(paths)
    (lp, rp) = sides
    if len(lp) != len(rp):
        raise StereoseedError(f"{' '.join(map(str, left))}: {len(lp)} images, but {' '.join(map(str, right))}: "
                              f"{len(rp)}; a rig's two cameras take their images together (image k of each)")
    shared = {p.name for p in lp} & {p.name for p in rp}
    lname, rname = (lp[0].parent.name, rp[0].parent.name) if lp else ("", "")
    if lname == rname:
        lname, rname = "left", "right"

    def name(path: Path, prefix: str) -> str:
        return f"{prefix}_{path.name}" if path.name in shared else path.name

    entries = [p for pair in zip(lp, rp) for p in pair]
    names = [n for a, b in zip(lp, rp) for n in (name(a, lname), name(b, rname))]
    return entries, names


def _sequence_entries(sources: list, video: VideoConfig, keyframes_to: str | Path | None
                      ) -> tuple[list, list[str]]:
    """(paths, or keyframe images in memory when ``keyframes_to`` is None; their names) of the
    sources in order."""
    entries: list = []
    names: list[str] = []

    videos: dict[str, Path] = {}

    def add(path: Path) -> None:
        check_image_name(path, path)
        if path.suffix.lower() in VIDEO_EXTENSIONS:
            if path.stem in videos:  # their keyframes would be named, and written, alike
                raise StereoseedError(f"{path}: a second video named {path.stem!r} (the first: {videos[path.stem]}); "
                                      f"rename one of them")
            videos[path.stem] = path
            keyframes = read_keyframes(path, video, keyframes_to)
            entries.extend(k.entry for k in keyframes)
            names.extend(k.name for k in keyframes)
        else:
            entries.append(path)
            names.append(path.name)

    for source in map(Path, sources):
        if source.is_file() and (source.suffix.lower() in VIDEO_EXTENSIONS
                                 or (len(sources) > 1 and source.suffix.lower() in IMAGE_EXTENSIONS)):
            add(source)
        else:
            for path in list_images(source):
                add(path)
    return entries, names


def save_outputs(recon: Reconstruction, report: dict[str, Any], out_dir: str | Path, cfg: Config = Config(),
                 lenses: list | None = None, dense: Any = None,
                 source: CorrespondenceSource | None = None, mesh: Any = None) -> dict[str, Path]:
    """The result folder (:func:`stereoseed.output.results.write_result`: cameras.json, tracks.npz,
    sparse.ply, cameras.ply, report.json) and report.html (:mod:`stereoseed.output.report.html`);
    atomic writes. lenses: the calibration's two lenses (:func:`stereoseed.calibration.lens_calibration.read_lenses`)
    when the images were undistorted: cameras.json then says how to map back to the photos.
    dense: the :class:`~stereoseed.dense.densify.DenseCloud` (shown in report.html) when the dense
    stage ran; source: what matches the weakest insertion's images again for report.html
    (default :class:`HarrisZncc`); mesh: the :class:`~stereoseed.dense.mesh.Mesh` of the dense
    cloud, shown in report.html (the caller writes mesh.ply)."""
    written = write_result(recon, report, out_dir, cfg, lenses)
    written["report_html"] = write_report_html(recon, report, out_dir, dense, source or HarrisZncc.of(cfg),
                                               mesh=mesh)
    return written


def reconstruct_to_folder(images_source: str | list[str], calib_path: str, out: str | Path, cfg: Config = Config(),
                          dense: bool = False, resume: bool = False, progress: Progress | None = None,
                          pool: JobPool | None = None, dense_progress: Progress | None = None,
                          rig_right: str | list[str] | None = None, mesh: bool = False,
                          unit: str | None = None) -> dict[str, Any]:
    """A whole run from files to a result folder: :func:`load_sequence`, :func:`reconstruct`
    (checkpointed in the staging folder), the dense stage when ``dense`` (its pair jobs on
    ``pool``, default local processes), :func:`save_outputs`. The folder is written as a whole
    (:class:`stereoseed.output.result_set.ResultSet`), by one run at a time (a second run on it
    is refused at once): on failure it keeps what it held, and after an interruption, or a full
    disk, the staging folder keeps the checkpoint for ``resume``. Returns the report.
    progress: called after the pair and after each insertion; dense_progress: as each of the
    dense stage's pairs comes in (:func:`stereoseed.dense.densify.densify`). The report's
    "timing": the command's wall time up to the writing of the results and its stages'; its
    "unit": the calibration's, else ``unit`` (:func:`stereoseed.io.files.read_calibration_unit`). rig_right: the
    right camera's images of a stereo rig walked with both cameras (:func:`load_sequence`). mesh:
    the dense cloud meshed into ``mesh.ply`` too (:func:`stereoseed.dense.mesh.mesh_result`; needs
    ``dense`` and the mesh extra, checked before any work)."""
    t0 = time.perf_counter()
    if mesh:
        from stereoseed.dense.mesh import require_meshing

        if not dense:
            raise StereoseedError("a mesh is made from the dense cloud: add --dense")
        require_meshing()
    sources = [images_source] if isinstance(images_source, (str, Path)) else list(images_source)
    with ResultSet(out) as results:  # before any staging folder is touched
        results.check()  # before any work: never clobber what the user made
        _refuse_output_over_inputs(results, [*sources, calib_path])
        # a resumed run takes only its checkpoint from the staging folder: every output is written again
        staging = results.open(keep=(CHECKPOINT, CHECKPOINT + SPILL_SUFFIX) if resume else ())
        try:
            # a video's keyframes are kept with the result, which names them
            images, names, P_pair, lenses = load_sequence_and_lenses(images_source, calib_path, cfg.video,
                                                                     staging / "keyframes", rig_right=rig_right,
                                                                     ordering=cfg.ordering)
            _refuse_output_over_inputs(results, [images.source(i) for i in range(len(images))])
            unit = read_calibration_unit(calib_path, unit)
        except BaseException:
            if not resume:  # a resumed run's checkpoint outlives a mistyped input
                results.abandon()
            raise
        try:
            stages = {"loading": time.perf_counter() - t0}
            recon, report = reconstruct(images, names, P_pair, cfg, progress=progress,
                                        checkpoint=staging / CHECKPOINT, resume=resume, rig=rig_right is not None)
            stages["sparse"] = time.perf_counter() - t0 - sum(stages.values())
            if dense:
                from stereoseed.dense.densify import densify  # the dense stage's modules only for a dense run

                cloud, report["dense"] = densify(recon, cfg, staging, pool, dense_progress)
                stages["dense"] = time.perf_counter() - t0 - sum(stages.values())
            else:
                cloud = None
            surface = None
            if mesh:  # from the cloud in memory: report.html shows it
                from stereoseed.dense.mesh import poisson_mesh, write_mesh

                surface, report["mesh"] = poisson_mesh(cloud.points, cloud.normals, cloud.colors, cfg.mesh,
                                                         cloud.confidence)
                write_mesh(staging / "mesh.ply", surface)
                stages["mesh"] = time.perf_counter() - t0 - sum(stages.values())
            report.update(unit=unit, timing={"total_s": time.perf_counter() - t0, "stages_s": stages})
            save_outputs(recon, report, staging, cfg, lenses, cloud, mesh=surface)
            # the photos, so the exports that need them find them (their paths relative to ``out``)
            write_inputs(staging, out, [images.source(i) for i in range(len(images))], names, rig_right is not None)
            results.commit(drop=(".checkpoint*",))  # this run's checkpoint and any stale one
        except KeyboardInterrupt:
            raise  # the staging folder keeps the checkpoint: resume continues
        except BaseException as e:
            full = _disk_full(e)
            if full is None:
                results.abandon()
                raise
            raise StereoseedError(f"{results.shown}: the disk is full ({full}); the run so far is kept in "
                                  f"{results.staging}: free some space, then run the same command with --resume "
                                  f"to continue") from None
    return report


def _refuse_output_over_inputs(results: ResultSet, inputs: list) -> None:
    """Refuse a result folder that is the current folder, holds it, or holds an input: the
    folder is replaced as a whole when the run ends (and a resumed run reads its inputs
    again)."""
    try:
        here = Path(os.path.realpath(os.getcwd()))
    except OSError:  # the current folder was removed: nothing of it to replace
        here = None
    if here is not None and (results.path == here or results.path in here.parents):
        raise StereoseedError(f"{results.shown}: is the current folder or holds it; the result folder is replaced "
                              f"as a whole: give a new folder for the results")
    for item in inputs:
        if isinstance(item, (str, Path)) and str(item) != "memory":
            where = Path(os.path.realpath(item))
            if results.path == where or results.path in where.parents:
                raise StereoseedError(f"{results.shown}: holds the input {item}; the result folder is replaced as a "
                                      f"whole: give another folder for the results")


def _disk_full(error: BaseException) -> str | None:
    """The system's words when ``error`` comes of a full disk or quota (itself or what it was
    raised from), else None."""
    seen: set[int] = set()
    e: BaseException | None = error
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)):
            return e.strerror or "no space left on the device"
        e = e.__cause__ or e.__context__
    return None
