"""stereoseed: incremental multi-view 3D reconstruction seeded by a calibrated stereo pair.

``stereoseed.calibrate``, ``stereoseed.reconstruct``, ``stereoseed.load_result``, ``Result`` and
``Config``: the Python API (:mod:`stereoseed.api`). Importing the package loads neither NumPy
nor the pipeline: the API's module is imported when one of its names is first used (the
command sets NumPy's BLAS threads before NumPy loads)."""
from typing import TYPE_CHECKING

from stereoseed.config import Config

__version__ = "0.1.0"
__all__ = ["calibrate", "reconstruct", "load_result", "Result", "PairCalibration", "Config", "__version__"]

_API = {"calibrate", "reconstruct", "load_result", "Result", "PairCalibration"}

if TYPE_CHECKING:  # what the names are, for type checkers and editors
    from stereoseed.api import PairCalibration, Result, calibrate, load_result, reconstruct


def __getattr__(name: str):
    if name in _API:
        from stereoseed import api

        value = getattr(api, name)
        globals()[name] = value  # found once
        return value
    raise AttributeError(f"module 'stereoseed' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | _API)
