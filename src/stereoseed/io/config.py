"""How a video becomes a sequence of keyframes (:mod:`stereoseed.io.video`).

Every default states its source (see :mod:`stereoseed.config`)."""
from __future__ import annotations

from dataclasses import dataclass

from stereoseed.validation import positive, whole

__all__ = ['VideoConfig']


@dataclass(frozen=True)
class VideoConfig:
    """Keyframes of a walk filmed as a video (:mod:`stereoseed.io.video`)."""

    # a keyframe once the tracked points moved by this fraction of the image width (median) since
    # the last one: the matcher searches 25 % of the width (paper), so consecutive keyframes stay
    # well inside its window while the parallax grows (about 5-10 degrees of a walk around an
    # object at a few object sizes)
    keyframe_motion: float = 0.08
    # or sooner, when fewer than this fraction of the points tracked since the last keyframe are
    # still tracked (a fast turn, an occlusion): the next keyframe must still share points
    min_tracked_fraction: float = 0.5
    # the keyframe is the sharpest (variance of the Laplacian, Pech-Pacheco et al. 2000) of the
    # last frames past 3/4 of the motion: a blurred frame loses its interest points
    sharpest_of: int = 6
    tracked_points: int = 400  # corners tracked by pyramidal Lucas-Kanade (Shi-Tomasi 1994)
    tracking_width: int = 640  # px: frames are tracked at most this wide (speed; keyframes stay full size)

    def __post_init__(self) -> None:
        if not 0.0 < self.keyframe_motion < 0.25:
            raise ValueError(f"VideoConfig.keyframe_motion must be in (0, 0.25) (the matcher's window), "
                             f"got {self.keyframe_motion!r}")
        if not 0.0 < self.min_tracked_fraction < 1.0:
            raise ValueError(f"VideoConfig.min_tracked_fraction must be in (0, 1), got {self.min_tracked_fraction!r}")
        whole(self, "sharpest_of", "tracked_points", "tracking_width")
        positive(self, "sharpest_of", "tracked_points", "tracking_width")
