"""Where the mapper's correspondences come from: interest points, pair matches, sub-pixel
refinement and tracking by patch alignment.

:class:`HarrisZncc` is the paper's source (Harris interest points matched by ZNCC under the
epipolar constraint, a known or a robust F). Any object with the methods of
:class:`CorrespondenceSource` can replace it: the tests and benchmarks feed the same mapper
with the exact correspondences of a synthetic scene (``evaluation.TrueCorrespondences``) to
measure the chain alone.
"""
from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Any, Callable, Protocol

import numpy as np

from stereoseed.features.config import FeatureConfig
from stereoseed.features.harris import Features, describe, extract_features
from stereoseed.matching.config import MatchingConfig
from stereoseed.matching.alignment import PairCache, align_matches, refine_features
from stereoseed.matching.containers import Matches
from stereoseed.matching.pair import match_pair
from stereoseed.sfm.config import TrackingConfig
from stereoseed.threads import may_overlap

__all__ = ["CorrespondenceSource", "OPTIONAL", "optional", "HarrisZncc", "Prefetching"]


class CorrespondenceSource(Protocol):
    """What the mapper asks of a correspondence source. ``refine`` and ``track`` are optional
    (without them matched points keep their detected positions and nothing is tracked);
    ``turns_images`` says whether matching an image turned by 180 degrees can find more
    (a rotation-sensitive matcher such as ZNCC); ``expect_match(a, fa, image_width, b)``, optional,
    hears that view a's interest points are final (:class:`Prefetching` then matches them with
    image b's, the next by default, ahead of time, while ``track`` may be called: tracking must
    not change what matching reads or writes)."""

    def features(self, index: int, image: np.ndarray) -> Features:
        """Interest points of image ``index``."""

    def match(self, a: int, b: int, fa: Features, fb: Features, F: np.ndarray | None, image_width: int) -> Matches:
        """Matches between views a and b; F (3, 3) when both cameras are known."""


# The protocol's optional members and what a source without them stands for: no refinement of
# matched points, no tracking, no announcement of final points, no pair cache, a matcher that
# turning an image does not help.
OPTIONAL: dict[str, Any] = {"refine": None, "track": None, "expect_match": None, "pair_cache": None,
                            "turns_images": False}


def optional(source: CorrespondenceSource, name: str) -> Any:
    """The optional member ``name`` of ``source`` (:data:`OPTIONAL`), or its default."""
    return getattr(source, name, OPTIONAL[name])


class HarrisZncc:
    """The paper's correspondences: Harris interest points, ZNCC matches under the epipolar
    constraint (known F) or a robust F, refined and tracked by affine patch alignment."""

    turns_images = True  # ZNCC is not rotation invariant

    def __init__(self, features: FeatureConfig, matching: MatchingConfig, tracking: TrackingConfig):
        self.feature_config, self.matching, self.tracking = features, matching, tracking
        self._pair_caches: list[PairCache] = []

    @classmethod
    def of(cls, sections: Any) -> "HarrisZncc":
        """The source of a configuration's sections ``features``, ``matching`` and ``tracking``
        (a :class:`stereoseed.config.Config`, a :class:`stereoseed.sfm.options.MapperOptions`)."""
        return cls(sections.features, sections.matching, sections.tracking)

    def pair_cache(self, fa: Features, fb: Features) -> PairCache:
        """The cache of the pair (fa, fb): an insertion matches its pair up to four times and
        then refines it, over largely the same candidates. The last two pairs only: a cache
        holds both feature sets (with their grey images), their scored candidate pairs and
        alignments."""
        for c in self._pair_caches:
            if c.covers(fa, fb):
                return c
        self._pair_caches = self._pair_caches[-1:] + [PairCache(fa, fb)]
        return self._pair_caches[-1]

    def features(self, index: int, image: np.ndarray) -> Features:
        return extract_features(image, self.feature_config, patch_size=self.matching.patch_size)

    def match(self, a: int, b: int, fa: Features, fb: Features, F: np.ndarray | None, image_width: int) -> Matches:
        """Strict localisation check first; a pair that keeps fewer than ``relax_below`` matches
        (real images: plaster, lighting, strong foreshortening) is matched again with the
        relaxed check and robust estimation takes care of the extra outliers."""
        mc = self.matching
        cache = self.pair_cache(fa, fb)
        m = match_pair(fa, fb, mc, F=F, image_width=image_width, cache=cache).matches
        if len(m) < mc.relax_below:
            relaxed = match_pair(fa, fb, mc.relaxed(), F=F, image_width=image_width, cache=cache).matches
            if len(relaxed) > len(m):
                m = relaxed
        return m

    def refine(self, fa: Features, fb: Features, m: Matches) -> Features:
        """fb with its matched points moved onto their partners in fa (sub-pixel affine
        alignment): a track followed pair after pair then carries one physical point, not
        detector noise."""
        return refine_features(fa, fb, m, self.matching, cache=self.pair_cache(fa, fb))

    def track(self, ref: int, target: int, f_ref: Features, ref_idx: np.ndarray, f_target: Features,
              predicted: np.ndarray, max_shift_px: float) -> tuple[np.ndarray, np.ndarray]:
        """Find interest points ``ref_idx`` (K,) of a reference view in a target view, starting at
        their predicted pixels (K, 2): affine alignment of the reference patch (no detector
        involved, so a track survives where Harris does not fire again). Returns (xy (K, 2), ok (K,))."""
        predicted = np.asarray(predicted, np.float64)
        ref_idx = np.asarray(ref_idx, np.int64)
        # a cheap first look (unaligned ZNCC at the prediction) rejects occluded points before
        # the ~20x dearer alignment
        desc, valid = describe(f_target.gray, predicted, f_target.patch_size)
        look = np.flatnonzero(valid & f_ref.valid[ref_idx]
                              & (np.einsum("ij,ij->i", desc, f_ref.desc[ref_idx]) >= self.tracking.first_look_zncc))
        xy, ok = predicted.copy(), np.zeros(len(predicted), bool)
        probe = Features(predicted[look], desc[look], valid[look], np.zeros(len(look)), f_target.image_shape, f_target.gray)
        m = Matches(ref_idx[look], np.arange(len(look)), np.ones(len(look)))
        al = align_matches(f_ref, probe, m, self.matching)
        xy[look] = al.x2
        ok[look] = (al.converged & (al.shift(probe, m) <= max_shift_px)
                    & (al.zncc > self.tracking.min_aligned_zncc))
        return xy, ok


# The source's methods that may run while a speculative match does: tracking only reads interest
# points and images (HarrisZncc.track aligns patches without the pair caches matching fills;
# TrueCorrespondences.track reads the ids its features recorded). The mapper tracks the older
# views' points into the new view, announces its interest points final, then tracks the new
# view's points back into the older views: that second half overlaps the next match.
_BESIDE_MATCHING = ("track",)


@dataclass(frozen=True)
class _Speculation:
    """A match of view a (interest points ``fa``) with a later image b, computed ahead: the
    future gives (b's interest points, the matches)."""

    a: int
    b: int
    fa: Features
    image_width: int
    future: Future

    def answers(self, a: int, b: int, fa: Features, fb: Features, image_width: int) -> bool:
        """Whether it is this call's: the same views, the very same feature sets and width, and
        no error (a failed speculation is not reported: the direct call fails the same way if it
        was this one)."""
        return ((self.a, self.b, self.image_width) == (a, b, image_width) and self.fa is fa
                and self.future.exception() is None and self.future.result()[0] is fb)


class Prefetching:
    """A correspondence source that works ahead of the mapper in background threads
    (``image_of(index)`` gives the image of view ``index``):

    * the interest points of the next images (they depend on their image alone);
    * the matches of a view with the next image (a rig's: the next station's image of its side),
      once the mapper says the view's interest points are final (:meth:`expect_match`): the
      next insertion starts with exactly that call (robust F, no camera yet), so it runs while
      the mapper adjusts the view just placed.

    OpenCV and the Numba kernels release the GIL, so on two cores this work overlaps the
    geometry. Results are those of the wrapped source, bit for bit: a speculative match is
    used only for the very feature sets it was computed on, and every other call to the source
    but ``features`` (which keeps no state) and ``track`` (which shares nothing with matching)
    first waits for it: the source's caches are never shared between threads. ``first``: the first index
    to prefetch; ``ahead``: how many images ahead (each holds its interest points and grey
    image until asked for). Use as a context manager: the threads stop (pending work
    cancelled) on exit."""

    def __init__(self, source: Any, image_of: Callable[[int], np.ndarray], n_images: int, first: int, ahead: int = 2):
        self.source = source
        self._image_of = image_of
        self._n = n_images
        self._next = first
        self._ahead = ahead
        self._futures: dict[int, Future] = {}
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="stereoseed-features")
        self._matcher = ThreadPoolExecutor(max_workers=1, thread_name_prefix="stereoseed-matching")
        self._speculation: _Speculation | None = None
        self._submit_up_to(first + ahead - 1)

    def __getattr__(self, name: str) -> Any:
        """The source's attribute (turns_images; refine, track, pair_cache where it has them),
        its methods called once the speculative match is over, but ``track``, which runs beside
        it (:data:`_BESIDE_MATCHING`)."""
        attr = getattr(self.source, name)
        if not callable(attr) or name in _BESIDE_MATCHING:
            return attr

        def settled(*args: Any, **kwargs: Any) -> Any:
            self._settle()
            return attr(*args, **kwargs)

        return settled

    def _features_of(self, index: int) -> tuple[np.ndarray, Features]:
        image = self._image_of(index)
        return image, self.source.features(index, image)

    def _submit_up_to(self, last: int) -> None:
        while self._next <= min(last, self._n - 1):
            self._futures[self._next] = self._executor.submit(self._features_of, self._next)
            self._next += 1

    def features(self, index: int, image: np.ndarray) -> Features:
        self._submit_up_to(index + self._ahead)
        for done in [i for i in self._futures if i < index]:  # the walk has moved past them
            del self._futures[done]
        # kept until the walk moves on: a rig's right image is asked for again at its own insertion
        future = self._futures.get(index)
        if future is not None:
            fetched, features = future.result()
            if fetched is image or np.array_equal(fetched, image):  # not a turned copy
                return features
        return self.source.features(index, image)

    def expect_match(self, a: int, fa: Features, image_width: int, b: int | None = None) -> None:
        """View a's interest points ``fa`` are final: match them with image b's (default the
        next, a + 1) in the background, as :meth:`match` with no F will be asked to."""
        self._settle()
        b = a + 1 if b is None else b
        future = self._futures.get(b)
        if future is None or not may_overlap():  # the last image, or nothing to overlap with
            return

        def speculate() -> tuple[Features, Matches]:
            fb = future.result()[1]
            return fb, self.source.match(a, b, fa, fb, None, image_width)

        self._speculation = _Speculation(a, b, fa, image_width, self._matcher.submit(speculate))

    def _settle(self) -> _Speculation | None:
        """Wait for the speculative match (the source then is this thread's again); it is
        handed over, once."""
        speculation, self._speculation = self._speculation, None
        if speculation is not None:
            wait([speculation.future])
        return speculation

    def match(self, a: int, b: int, fa: Features, fb: Features, F: np.ndarray | None, image_width: int) -> Matches:
        speculation = self._settle()
        if speculation is not None and F is None and speculation.answers(a, b, fa, fb, image_width):
            return speculation.future.result()[1]
        return self.source.match(a, b, fa, fb, F, image_width)

    def __enter__(self) -> "Prefetching":
        return self

    def __exit__(self, *exc: object) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)
        self._matcher.shutdown(wait=True, cancel_futures=True)
        self._futures.clear()
        self._speculation = None
