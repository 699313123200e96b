"""stereoseed: incremental multi-view 3D reconstruction seeded by a calibrated stereo pair."""
from stereoseed.config import Config

__version__ = "0.1.0"
__all__ = ["Config", "__version__"]
