"""The two ways of growing the reconstruction once a view is registered: the paper's and ours.

* :class:`PaperMode` (the paper, §4.2-4.3): every match of I_{k-1} <-> I_k gives a new
  two-view point (S_{k-1,k}); the chained old points enter the BA cost through their
  observation in I_k, but their interest points keep standing for the new points, which the
  next insertion chains through (paper.md §4); the local BA frees P_k and the new points over
  the last three images; nothing more at the end unless asked.
* :class:`AccurateMode`: multi-view tracks (chained points linked, only unchained matches
  triangulated, points followed into the window by projection and re-triangulated from their
  whole track), a window of W cameras adjusted together (Mouragnon et al. 2006), and at the end
  loop closure and a global BA (holding the calibrated intrinsics when no image zoomed).
"""
from __future__ import annotations

from typing import Any, Callable, Protocol

import numpy as np

from stereoseed.arrays import unique
from stereoseed.estimators.config import TriangulationConfig
from stereoseed.sfm.config import MODE_DEFAULTS, ModeDefaults, PipelineConfig
from stereoseed.sfm.correspondence import CorrespondenceSource
from stereoseed.sfm.loop_closure import close_loop
from stereoseed.matching.containers import Matches
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.sfm.refinement import adjust, ba_report, global_adjust
from stereoseed.sfm.options import MapperOptions
from stereoseed.sfm.registration.base import implausible_motion
from stereoseed.sfm.tracks import add_two_view_points, retriangulate, track_by_projection
from stereoseed.geometry.models import CameraModel

__all__ = ["Mode", "PaperMode", "AccurateMode", "holds_intrinsics", "adjust_globally"]

PAPER_COST_IMAGES = 3  # eq. 12: the local BA's cost runs over the last three images


class Mode(Protocol):
    """How the reconstruction grows once a view is registered, and the defaults the mode gives
    the configuration (:data:`stereoseed.sfm.config.MODE_DEFAULTS`)."""

    name: str
    defaults: ModeDefaults

    def add_points(self, recon: Reconstruction, prev: int, k: int, m: Matches, chained: np.ndarray,
                   consistent: np.ndarray, chain_points: np.ndarray, triangulation: TriangulationConfig
                   ) -> np.ndarray: ...

    def grow_tracks(self, recon: Reconstruction, source: CorrespondenceSource, k: int, chain_points: np.ndarray,
                    options: MapperOptions, features_final: Callable[[], None] = lambda: None) -> dict[str, Any]: ...

    def local_adjust(self, recon: Reconstruction, prev: int, k: int, new_points: np.ndarray,
                     chain_points: np.ndarray, options: MapperOptions) -> dict[str, Any]: ...

    def adjustment_options(self, recon: Reconstruction, options: MapperOptions) -> MapperOptions: ...

    def next_match(self, k: int) -> int | None:
        """The view whose match with view k (robust F, no camera yet) the next insertion asks
        for first, to be computed ahead; None: none."""
        ...

    def finish(self, recon: Reconstruction, options: MapperOptions, source: CorrespondenceSource) -> dict[str, Any]: ...


class PaperMode:
    name = "paper"
    defaults = MODE_DEFAULTS["paper"]

    def add_points(self, recon: Reconstruction, prev: int, k: int, m: Matches, chained: np.ndarray,
                   consistent: np.ndarray, chain_points: np.ndarray, triangulation: TriangulationConfig
                   ) -> np.ndarray:
        """Observations of the chained points in k (unlinked) and a new two-view point per match.
        m: the guided matches prev <-> k; chained (M,): prev's interest point stands for a live
        point; consistent (M,): chained and reprojecting within the resection threshold, whose
        points are ``chain_points``. Returns the new point ids."""
        recon.add_observations(k, m.idx2[consistent], chain_points, link=False)
        return add_two_view_points(recon, prev, k, m, triangulation, colour_view=k, link_a=False)

    def grow_tracks(self, recon: Reconstruction, source: CorrespondenceSource, k: int, chain_points: np.ndarray,
                    options: MapperOptions, features_final: Callable[[], None] = lambda: None) -> dict[str, Any]:
        """The paper's points stay two-view points (k's interest points are final already)."""
        features_final()
        return {}

    def local_adjust(self, recon: Reconstruction, prev: int, k: int, new_points: np.ndarray,
                     chain_points: np.ndarray, options: MapperOptions) -> dict[str, Any]:
        """Eq. 12: P_k and the new points free, the cost over the last three images. With few
        chained points the new camera and its two-view points can slide together (the plain
        box: 9 chained observations, the camera 680 m away): an adjusted camera that could not
        follow the previous one keeps its resection."""
        view = recon.views[k]
        window = [k] + recon.registered_before(k, PAPER_COST_IMAGES - 1)
        P_resected, X_new = view.P.copy(), recon.points[new_points].copy()
        ba = ba_report(adjust(recon, options.bundle, options.pipeline.camera_model, free_views=[k],
                              free_points=new_points, views_in_cost=window))
        why = implausible_motion(view.P, recon.views[prev], recon.points[chain_points], k - prev,
                                 options.registration.max_zoom_step)
        if why:
            view.P, recon.points[new_points] = P_resected, X_new
            ba["refused"] = f"{view.name}: {why}"
        return ba

    def adjustment_options(self, recon: Reconstruction, options: MapperOptions) -> MapperOptions:
        """The paper's BA adjusts the run's camera model."""
        return options

    def next_match(self, k: int) -> int | None:
        """The next image: the next insertion matches it with k."""
        return k + 1

    def finish(self, recon: Reconstruction, options: MapperOptions, source: CorrespondenceSource) -> dict[str, Any]:
        """One global BA when asked (``ba="final"``)."""
        return {"final_ba": adjust_globally(recon, options)[0]} if options.pipeline.ba == "final" else {}


class AccurateMode:
    name = "accurate"
    defaults = MODE_DEFAULTS["accurate"]

    def add_points(self, recon: Reconstruction, prev: int, k: int, m: Matches, chained: np.ndarray,
                   consistent: np.ndarray, chain_points: np.ndarray, triangulation: TriangulationConfig
                   ) -> np.ndarray:
        """The chained points' tracks grow into k; the other matches become new points."""
        recon.add_observations(k, m.idx2[consistent], chain_points)
        new = m.subset(~chained & (recon.views[k].point_of_feature[m.idx2] < 0))
        return add_two_view_points(recon, prev, k, new, triangulation, colour_view=k)

    def grow_tracks(self, recon: Reconstruction, source: CorrespondenceSource, k: int, chain_points: np.ndarray,
                    options: MapperOptions, features_final: Callable[[], None] = lambda: None) -> dict[str, Any]:
        """The points of the window's older views searched in k and k's points in them; every
        point whose track grew (``chain_points`` too) re-triangulated from its whole track.
        ``features_final`` is called as soon as k's interest points are (once the points are
        tracked into k: the rest adds interest points to the older views only)."""
        older = recon.registered_before(k, options.pipeline.window + 1)
        tracked = [track_by_projection(recon, k, older, options.tracking, source)]
        features_final()
        tracked += [track_by_projection(recon, j, [k], options.tracking, source) for j in older]
        tracked = np.concatenate(tracked)
        grown = np.concatenate([chain_points, tracked])
        if options.pipeline.retriangulate and len(grown):
            retriangulate(recon, unique(grown), options.triangulation)
        return {"tracked_observations": int(len(tracked))}

    def local_adjust(self, recon: Reconstruction, prev: int, k: int, new_points: np.ndarray,
                     chain_points: np.ndarray, options: MapperOptions) -> dict[str, Any]:
        """The last W registered cameras and every point they see."""
        return ba_report(adjust(recon, options.bundle, options.pipeline.camera_model,
                                free_views=recon.registered_views[-options.pipeline.window:]))

    def adjustment_options(self, recon: Reconstruction, options: MapperOptions) -> MapperOptions:
        """The options of the BA after an insertion: ``options`` with the "fixed" camera model
        (the calibrated intrinsics, pose only) while :func:`holds_intrinsics`, else ``options`` itself.

        The final BA's no-zoom hold, applied from the start: a small object seen with a long
        focal length barely tells the focal length from the distance, and a free focal length
        per window drifts. dinoSparseRing: the local BAs took the focal length from 3310 px (the
        truth) to 3397, 3649, 4401 px over three insertions while the cameras moved away (a
        camera resected 3 mm off was 17 mm off after its BA, the next 17 -> 67 mm); the next
        resection's no-zoom hypothesis starts from the drifted focal length and keeps it."""
        return options.held() if holds_intrinsics(recon, options.pipeline) else options

    next_match = PaperMode.next_match

    def finish(self, recon: Reconstruction, options: MapperOptions, source: CorrespondenceSource) -> dict[str, Any]:
        """Loop closure, then one global BA unless closing the loop ran one. When no image's
        resection found a zoom (``hold_unzoomed``, the "focal" model), that global BA holds
        every image at the calibrated intrinsics: one lens setting for the whole sequence (a
        focal length per image only trades against the depth); "no_zoom" in the report."""
        pc = options.pipeline
        out: dict[str, Any] = {}
        adjusted = False  # closing the loop ran a global BA
        if pc.loop_closure:
            adjusted, out["loop_closure"] = close_loop(recon, options.loop_closure, options.resection, source,
                                                       lambda r: adjust_globally(r, options))
        later = [v for v in recon.registered_views if v > 1]
        if later and holds_intrinsics(recon, pc) and (adjusted or pc.ba == "final"):
            out["no_zoom"] = True
            out["final_ba"] = adjust_globally(recon, options.held())[0]
        elif pc.ba == "final" and not adjusted:
            out["final_ba"] = adjust_globally(recon, options)[0]
        return out


def holds_intrinsics(recon: Reconstruction, pipeline: PipelineConfig, besides: int | None = None) -> bool:
    """Whether the run holds the calibrated intrinsics: the "focal" model with
    ``PipelineConfig.hold_unzoomed``, and no image after the pair (``besides`` that view) found
    zoomed by its resection."""
    pc = pipeline
    return (pc.hold_unzoomed and pc.camera_model == CameraModel.FOCAL
            and not any(recon.views[v].zoomed for v in recon.registered_views if v > 1 and v != besides))


def adjust_globally(recon: Reconstruction, options: MapperOptions) -> tuple[dict[str, Any], int]:
    """:func:`stereoseed.sfm.refinement.global_adjust` under ``options`` (their camera model:
    the run's, or "fixed" when they hold the intrinsics)."""
    return global_adjust(recon, options.bundle, options.outliers, options.pipeline.camera_model)
