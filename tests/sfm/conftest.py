import pytest

from ring_helpers import ring
from stereoseed.config import Config
from stereoseed.sfm.mapper import insert_view, initialise


@pytest.fixture(scope="module")
def started():
    """A ring of 8 views, the pair and 2 insertions done (accurate mode)."""
    images, names, Ps, source = ring(8)
    cfg = Config()
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    for k in (2, 3):
        assert insert_view(recon, k, cfg, source)["status"] == "registered"
    return recon, Ps, cfg, source
