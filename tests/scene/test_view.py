"""A view: its camera in the frame of the image the run works on (turned by 180 degrees or not),
its image held or read again, and its state read from its history."""
import cv2
import numpy as np

from geometry_helpers import ring_camera
from stereoseed.geometry.models import CameraModel
from stereoseed.geometry.projection import compose_projection
from stereoseed.scene.view import View


def test_reference_intrinsics_follow_an_image_turned_upside_down():
    # The constrained camera models share the calibrated camera's principal point; in an image
    # turned by 180 degrees (View.rotated_180) it sits at (W - 1 - cx, H - 1 - cy).

    K = np.array([[1500.0, 0.0, 302.3], [0.0, 1498.0, 246.9], [0.0, 0.0, 1.0]])
    upright = View("a.png", image=np.zeros((480, 640, 3), np.uint8))
    turned = View("b.png", image=np.zeros((480, 640, 3), np.uint8), rotated_180=True)
    R = cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0]
    P_input = compose_projection(K, R, np.array([0.1, 0.0, 2.0]))
    turned.P = np.array([[-1.0, 0, 639], [0, -1.0, 479], [0, 0, 1]]) @ P_input  # the run's frame
    np.testing.assert_allclose(turned.K, turned.in_frame_of(K, upright), atol=1e-9)
    np.testing.assert_allclose(turned.P_input, P_input, atol=1e-12)
    np.testing.assert_allclose(upright.in_frame_of(turned.in_frame_of(K, upright), turned), K)
    assert upright.in_frame_of(K, upright) is K


def test_a_view_reads_its_image_again_or_holds_it_and_keeps_its_size():
    image = np.zeros((6, 8, 3), np.uint8)
    read = []
    lazy = View("a.png", load=lambda: read.append(1) or image)
    assert lazy.can_read_image_again and lazy.image_size == (8, 6) and read == [1]
    lazy.keep_image(image, rotated_180=False)  # it can read it again: not held
    assert lazy._image is None and lazy.image is image
    lazy.keep_image(image[::-1, ::-1].copy(), rotated_180=True)  # turned: only the run has it
    assert lazy._image is not None and lazy.rotated_180
    held = View("b.png", image=image)
    held.image = None
    assert not held.can_read_image_again and held.image_size == (8, 6)


def test_a_new_P_keeps_the_views_camera_model_and_a_fresh_view_is_pending():
    view = View("a.png", P=ring_camera(10.0)[3], camera_model=CameraModel.FOCAL)
    assert view.camera.model == CameraModel.FOCAL and view.registered
    view.P = ring_camera(20.0)[3]  # a refinement moves the camera within its model
    assert view.camera.model == CameraModel.FOCAL
    np.testing.assert_allclose(view.center, view.camera.centre)
    fresh = View("b.png")
    assert fresh.status == "pending" and fresh.history == () and fresh.reliable and fresh.found_by is None
