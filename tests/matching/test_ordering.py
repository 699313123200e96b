"""Photos in any order (issue #49): the walk recovered from the images' overlaps, the calibrated
pair first; a given walk kept; an order the images cannot support end to end left as given."""
import random

import numpy as np
import pytest

from stereoseed.matching.ordering import OrderingConfig, best_walk, thumbnail, walk_order, walk_strength


def _ring_overlap(n, reach=3, seed=0):
    """(n, n) overlaps of an open walk: images k apart overlap by 200 / k up to ``reach`` apart,
    with noise."""
    rng = np.random.default_rng(seed)
    ov = np.zeros((n, n), np.int64)
    for i in range(n):
        for j in range(i + 1, min(n, i + reach + 1)):
            ov[i, j] = ov[j, i] = int(200 / (j - i) + rng.integers(0, 20))
    return ov


def test_the_best_walk_of_a_shuffled_walk_is_the_walk():
    n = 14
    truth = _ring_overlap(n)
    perm = [0, 1] + random.Random(3).sample(range(2, n), n - 2)
    shuffled = truth[np.ix_(perm, perm)]
    found = best_walk(shuffled)
    assert [perm[i] for i in found] == list(range(n))
    assert walk_strength(list(range(n)), truth) == walk_strength(found, shuffled)


def test_a_shuffled_walk_of_photos_is_put_back_in_order_and_a_walk_is_kept(box_scene):
    scene = box_scene
    n = 7
    thumbs = [thumbnail(im, 320) for im in scene.images[:n]]
    order, why, doubt = walk_order(thumbs)
    assert order == list(range(n)) and why is None and doubt is None  # a walk in order is not second-guessed
    perm = [0, 1] + random.Random(1).sample(range(2, n), n - 2)
    order, why, _ = walk_order([thumbs[i] for i in perm])
    assert [perm[i] for i in order] == list(range(n)) and why
    assert walk_order([thumbs[i] for i in perm], OrderingConfig(mode="as-given"))[0] == list(range(n))


def test_an_order_the_images_cannot_support_end_to_end_is_left_as_given(monkeypatch):
    # a step of the walk that nothing matches across (the plain back of an object): no order is
    # guessed around it, since the mapper's motion prior may bridge it in the given order only
    import stereoseed.matching.ordering as ordering

    n = 10
    truth = _ring_overlap(n, reach=2)
    truth[4, 5] = truth[5, 4] = truth[3, 5] = truth[5, 3] = truth[4, 6] = truth[6, 4] = 0
    perm = [0, 1, 7, 3, 9, 2, 5, 8, 4, 6]
    monkeypatch.setattr(ordering, "overlaps", lambda thumbs, cfg: truth[np.ix_(perm, perm)])
    order, why, doubt = walk_order([np.zeros((8, 8), np.uint8)] * n)
    assert order == list(range(n)) and why is None
    assert "show no overlap" in doubt and "list them in the order they were taken" in doubt


def test_the_fountain_shuffled_is_put_back_in_walk_order(fountain_dir):
    import cv2

    folder = fountain_dir
    names = sorted(p.name for p in folder.glob("*.jpg"))
    perm = [0, 1] + random.Random(2).sample(range(2, len(names)), len(names) - 2)
    thumbs = [thumbnail(cv2.imread(str(folder / names[i])), 640) for i in perm]
    order, why, _ = walk_order(thumbs)
    assert [perm[i] for i in order] == list(range(len(names))), why


def test_a_folder_in_another_order_is_run_in_walk_order_and_a_list_as_written(box_scene, tmp_path):
    # the file names of a folder say nothing of the walk; a list file is an order someone wrote
    import cv2

    from scene_helpers import write_calib
    from stereoseed.pipeline import load_sequence

    n = 7
    perm = [0, 1] + random.Random(4).sample(range(2, n), n - 2)
    names = [f"photo_{k:02d}.png" for k in range(n)]  # name order: perm's
    folder = tmp_path / "photos"
    folder.mkdir()
    for name, i in zip(names, perm):
        cv2.imwrite(str(folder / name), box_scene.images[i])
    calib = write_calib(tmp_path / "calib.json", box_scene.P[:2])
    _, got, _ = load_sequence(str(folder), str(calib), ordering=OrderingConfig(thumbnail_px=320))
    assert got == [names[perm.index(k)] for k in range(n)]
    listing = tmp_path / "list.txt"
    listing.write_text("".join(f"photos/{name}\n" for name in names))
    assert load_sequence(str(listing), str(calib), ordering=OrderingConfig(thumbnail_px=320))[1] == names


def test_likeness_finds_a_shifted_view_alike_and_a_flat_or_unrelated_one_not():
    from stereoseed.matching.ordering import likeness

    rng = np.random.default_rng(0)
    big = (rng.random((60, 80)) * 255).astype(np.uint8)
    import cv2

    big = cv2.resize(cv2.GaussianBlur(big, (0, 0), 2.0), (400, 300))
    shifted = np.roll(big, (12, -20), axis=(0, 1))  # the same view a few per cent over
    unrelated = cv2.resize(cv2.GaussianBlur((rng.random((60, 80)) * 255).astype(np.uint8), (0, 0), 2.0), (400, 300))
    flat = np.full_like(big, 90)
    alike = likeness([big, shifted, unrelated, flat])
    assert alike[0, 1] > 0.9 and alike[0, 1] == alike[1, 0]
    assert alike[0, 2] < 0.5 and np.all(alike[3] == 0) and np.all(np.diag(alike) == 0)


def test_the_dino_and_temple_rings_shuffled_are_put_back_in_walk_order(dino_dir, temple_dir):
    # Turntable rings of dark or white, weakly textured objects: steps SIFT finds nothing across
    # (5 of dinoSparseRing's 15) are bridged by how alike the neighbouring views look
    import cv2

    for folder in (dino_dir, temple_dir):
        names = (folder / "ring_order.txt").read_text().split()
        perm = [0, 1] + random.Random(1).sample(range(2, len(names)), len(names) - 2)
        thumbs = [thumbnail(cv2.imread(str(folder / names[i])), 640) for i in perm]
        order, why, _ = walk_order(thumbs)
        got = [names[perm[i]] for i in order]
        # templeSR0001 and templeSR0011 were taken from one spot (the same published camera):
        # either may come first
        same_spot = {"templeSR0001.png", "templeSR0011.png"}
        assert all(a == b or {a, b} <= same_spot for a, b in zip(got, names)), (folder.name, got, why)


def test_a_walk_resting_on_likeness_replaces_a_given_order_only_when_clearly_stronger(monkeypatch):
    # SIFT leaves a gap in the given order and in every other; photos of one object all look
    # somewhat alike, so a walk bridged by likeness alone must beat the given order clearly
    import stereoseed.matching.ordering as ordering

    n = 8
    truth = _ring_overlap(n, reach=2)
    truth[3, 4] = truth[4, 3] = truth[2, 4] = truth[4, 2] = truth[3, 5] = truth[5, 3] = 0
    perm = [0, 1, 5, 3, 2, 7, 4, 6]  # the given order: a shuffle
    alike = np.full((n, n), 0.6)
    np.fill_diagonal(alike, 0.0)
    monkeypatch.setattr(ordering, "overlaps", lambda thumbs, cfg: truth[np.ix_(perm, perm)])
    monkeypatch.setattr(ordering, "likeness", lambda thumbs, cfg: alike)
    order, why, _ = walk_order([np.zeros((8, 8), np.uint8)] * n)
    assert order != list(range(n)) and "overlap by" in why  # the shuffle's total is far weaker
    in_order = truth.copy()
    monkeypatch.setattr(ordering, "overlaps", lambda thumbs, cfg: in_order)
    order, why, doubt = walk_order([np.zeros((8, 8), np.uint8)] * n)
    assert order == list(range(n)) and why is None  # the walk, its gap bridged by likeness: kept
