"""Shared fixtures: the data folder of real sequences and the rendered synthetic box scenes."""
from __future__ import annotations

import os

# The tests run as the command line does: one BLAS thread, set before NumPy loads OpenBLAS (see
# stereoseed.cli). Two pytest workers each with OpenBLAS's spinning threads spent a fifth of the
# suite's CPU waiting.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import logging  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from stereoseed.experiments.paper import noisy_images  # noqa: E402
from stereoseed.io.sample_data import find_sample, missing_message  # noqa: E402
from stereoseed.synthetic.scene import SceneConfig, SyntheticScene, render_scene  # noqa: E402


@pytest.fixture(autouse=True)
def _library_logging_as_found():
    """The library's logger as the test found it: a CLI test run in-process (``main([... --quiet])``)
    sets its level to ERROR and adds a handler, and a later test's caplog would see nothing."""
    logger = logging.getLogger("stereoseed")
    level, handlers = logger.level, list(logger.handlers)
    yield
    logger.setLevel(level)
    for h in [h for h in logger.handlers if h not in handlers]:
        logger.removeHandler(h)


# --- SHARED_DATA ------------------------------------------------------------------------------
def _sequence_dir(name: str) -> Path:
    path = find_sample(name)  # $STEREOSEED_DATA, else ../shared/data, else what data fetch wrote
    if path is None:
        pytest.skip(missing_message(name))
    return path


@pytest.fixture(scope="session")
def temple_dir() -> Path:
    """The Middlebury templeSparseRing folder; skips the test when it is absent."""
    return _sequence_dir("templeSparseRing")


@pytest.fixture(scope="session")
def dino_dir() -> Path:
    """The Middlebury dinoSparseRing folder; skips the test when it is absent."""
    return _sequence_dir("dinoSparseRing")


@pytest.fixture(scope="session")
def fountain_dir() -> Path:
    """Strecha's fountain-P11 folder; skips the test when it is absent."""
    return _sequence_dir("strechaFountainP11")


# --- synthetic scenes, rendered once per session ----------------------------------------------
@pytest.fixture(scope="session")
def box_scene() -> SyntheticScene:
    """The default textured 14-image ring around the box (SceneConfig())."""
    return render_scene(SceneConfig())


@pytest.fixture(scope="session")
def plain_box_scene() -> SyntheticScene:
    """The paper's plain box: uniform faces with only the dark squares, untextured ground."""
    return render_scene(SceneConfig(textured=False))


def _with_noise(scene: SyntheticScene, sigma: float) -> SyntheticScene:
    """What render_scene gives with noise_sigma=sigma, from the noise-free render: the renderer
    adds its noise after rendering, from a stream of its own (test_synthetic checks the bytes).
    A copy of the scene (its whole prefix): no array is shared with the clean one."""
    copy = scene.prefix(scene.n_images)
    return replace(copy, config=replace(copy.config, noise_sigma=sigma),
                   images=noisy_images(scene.images, sigma, scene.config.seed))


@pytest.fixture(scope="session")
def box_scene_noisy(box_scene) -> SyntheticScene:
    """The default ring with Gaussian image noise sigma = 2 grey levels."""
    return _with_noise(box_scene, 2.0)


@pytest.fixture(scope="session")
def small_box_scene() -> SyntheticScene:
    """The textured 14-image ring at 320 x 240 (one sample per pixel): for the tests whose
    subject does not depend on the image size and that run whole reconstructions again and
    again (kills, resumes, clusters); they take a prefix."""
    return render_scene(SceneConfig(width=320, height=240, focal_px=400.0, focal0_px=390.0, supersample=1))


@pytest.fixture(scope="session")
def plain_box_scene_noisy(plain_box_scene) -> SyntheticScene:
    """The plain box with Gaussian image noise sigma = 2 grey levels."""
    return _with_noise(plain_box_scene, 2.0)


@pytest.fixture(scope="session")
def temple_run(temple_dir):
    """templeSparseRing reconstructed in ring order, seeded by the par file's first two cameras
    (default config). Returns (reconstruction, report, true cameras in ring order)."""
    from stereoseed.io.files import read_middlebury_par
    from stereoseed.pipeline import load_sequence, reconstruct

    images, names, P_pair = load_sequence(str(temple_dir / "ring_order.txt"), str(temple_dir / "templeSR_par.txt"))
    truth = read_middlebury_par(temple_dir / "templeSR_par.txt")
    recon, report = reconstruct(images, names, P_pair)
    return recon, report, [truth[n] for n in names]


@pytest.fixture
def files(tmp_path):
    """Five small textured images on disk (80 x 60, band-limited noise): their paths."""
    from geometry_helpers import band_noise
    from stereoseed.io.files import write_image

    paths = []
    for i in range(5):
        image = (np.dstack([band_noise((60, 80), seed=i)] * 3) * 255).astype(np.uint8)
        paths.append(write_image(tmp_path / f"{i}.png", image))
    return paths
