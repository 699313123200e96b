"""Result containers of the matching stage: matches, patch alignments, a matched pair."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stereoseed.errors import StereoseedError
from stereoseed.features.harris import Features

__all__ = ["Matches", "Alignment", "PairMatches", "as_points"]


def as_points(kp: Features | np.ndarray) -> np.ndarray:
    """(N, 2) float64 positions of Features or of an array of points."""
    pts = kp.points if isinstance(kp, Features) else kp
    return np.asarray(pts, dtype=np.float64).reshape(-1, 2)


@dataclass(frozen=True)
class Matches:
    """Correspondences between two feature arrays.

    idx1: (M,) int64 indices into the points of image 1; idx2: (M,) int64 into image 2;
    score: (M,) float64 ZNCC of each match, higher is better (the resection chooses points by
    it): of the descriptor patches after :func:`~stereoseed.matching.zncc.match_zncc`, of the
    affinely aligned patches after :func:`~stereoseed.matching.alignment.filter_localization`.
    """

    idx1: np.ndarray
    idx2: np.ndarray
    score: np.ndarray

    def __post_init__(self) -> None:
        idx1 = np.asarray(self.idx1, dtype=np.int64).reshape(-1)
        idx2 = np.asarray(self.idx2, dtype=np.int64).reshape(-1)
        score = np.asarray(self.score, dtype=np.float64).reshape(-1)
        if not (idx1.shape == idx2.shape == score.shape):
            raise StereoseedError(
                f"Matches arrays differ in length: {idx1.shape}, {idx2.shape}, {score.shape}"
            )
        object.__setattr__(self, "idx1", idx1)
        object.__setattr__(self, "idx2", idx2)
        object.__setattr__(self, "score", score)

    @classmethod
    def empty(cls) -> Matches:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float64))

    def __len__(self) -> int:
        return int(self.idx1.shape[0])

    def subset(self, mask: np.ndarray) -> Matches:
        """The matches selected by a (M,) bool mask, an array of positions or a slice."""
        if not isinstance(mask, slice):
            mask = np.asarray(mask)
        return Matches(self.idx1[mask], self.idx2[mask], self.score[mask])

    def sorted_by_score(self) -> Matches:
        """The same matches, best ZNCC first."""
        return self.subset(np.argsort(-self.score, kind="stable"))

    def points(
        self, kp1: Features | np.ndarray, kp2: Features | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Matched positions: x1 (M, 2) float64 in image 1, x2 (M, 2) float64 in image 2."""
        return as_points(kp1)[self.idx1], as_points(kp2)[self.idx2]


@dataclass(frozen=True)
class Alignment:
    """Result of :func:`~stereoseed.matching.alignment.align_matches`, one row per match.

    x2: (M, 2) float64 position in image 2 of the point ``x1`` of image 1 (sub-pixel, from the
    affine alignment of the two patches); affine: (M, 2, 2) float64 local linear map from image 1
    to image 2 around the match; zncc: (M,) float64 ZNCC of the aligned patches (-1 where not
    converged); converged: (M,) bool.
    """

    x2: np.ndarray
    affine: np.ndarray
    zncc: np.ndarray
    converged: np.ndarray

    def shift(self, kp2: Features | np.ndarray, matches: Matches) -> np.ndarray:
        """(M,) distance between the aligned position and the detected point of image 2."""
        return np.linalg.norm(self.x2 - as_points(kp2)[matches.idx2], axis=1)


@dataclass(frozen=True)
class PairMatches:
    """Result of :func:`~stereoseed.matching.pair.match_pair`, whatever the path taken.

    matches: the kept :class:`Matches`, best score first (empty when no robust F was found);
    F: (3, 3) float64 fundamental matrix used (the given one) or estimated (unit norm), None when
    the robust estimate failed; stats: JSON-able counts per stage ("features" [N1, N2],
    "candidates", "localized", "ransac_inliers", "guided_candidates", "kept", the stages the path
    went through) and "geometry": "known F", "robust F" or "robust F failed: <reason>".
    """

    matches: Matches
    F: np.ndarray | None
    stats: dict = field(default_factory=dict)
