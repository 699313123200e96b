import numpy as np

from stereoseed.geometry.projection import camera_center, decompose_projection
from stereoseed.sfm.pair_consistency import centre_offset, left_out_pose, pair_consistency
from ring_helpers import walked


def test_a_pair_camera_off_the_walk_is_measured_where_the_walk_puts_it():
    """Left out, a camera of the pair is put by the rest of the walk where it is (within its
    noise); handed a copy of it 4 mm off, the walk puts the copy back by those 4 mm."""
    recon, _, _, _ = walked(6)
    found = pair_consistency(recon, (0, 1), 11.0, 3.0)
    assert set(found) == {recon.views[0].name, recon.views[1].name}
    for entry in found.values():
        assert entry["offset"] < 3 * entry["sigma"] + 1e-6 and entry["pairs"] >= 12
    K, R0, _ = decompose_projection(recon.views[0].P)
    off = {v: recon.views[v].P for v in recon.registered_views}
    off[0] = K @ np.hstack([R0, (-R0 @ (camera_center(recon.views[0].P) + [0.004, 0.0, 0.0]))[:, None]])
    refined, R, t = left_out_pose(recon, 0, 11.0, 3.0, cameras=off)
    moved, sigma = centre_offset(R, t, refined)
    assert abs(moved - 0.004) < max(3 * sigma, 2e-4) and sigma < 1e-3
