"""Cameras: look_at geometry, validation, JSON round trip."""

import json

import numpy as np
import pytest
import torch

from gca.render import Camera, CameraError, look_at


def test_look_at_puts_target_at_image_centre_and_up_is_up():
    cam = look_at(eye=[0.5, 0.8, -1.0], target=[0.5, 0.5, 0.5], up=[0, 1, 0], fov_deg=50, width=64, height=48)
    uv, z = cam.project(torch.tensor([[0.5, 0.5, 0.5], [0.5, 0.6, 0.5]], dtype=torch.float64))
    assert torch.allclose(uv[0], torch.tensor([32.0, 24.0], dtype=torch.float64), atol=1e-9)
    expected_z = np.linalg.norm(np.array([0.0, -0.3, 1.5]))
    assert z[0].item() == pytest.approx(expected_z)
    assert uv[1, 1] < uv[0, 1]            # a point higher in the world is higher (smaller v) in the image
    np.testing.assert_allclose(cam.center, [0.5, 0.8, -1.0], atol=1e-12)
    R = cam.w2c[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_horizontal_fov_sets_focal_length():
    cam = look_at([0, 0, -2], [0, 0, 0], [0, 1, 0], fov_deg=90, width=100, height=80)
    assert cam.K[0, 0] == pytest.approx(50.0) and cam.K[1, 1] == pytest.approx(50.0)
    # camera at -z looking at +z with y up: image right is world -x; 45 deg off axis lands on the border
    uv, _ = cam.project(torch.tensor([[-2.0, 0.0, 0.0]], dtype=torch.float64))
    assert uv[0, 0].item() == pytest.approx(100.0)


def test_json_round_trip():
    cam = look_at([1, 2, 3], [0.5, 0.5, 0.5], [0, 1, 0], 40, 33, 21)
    back = Camera.from_dict(json.loads(json.dumps(cam.to_dict())))
    np.testing.assert_array_equal(back.K, cam.K)
    np.testing.assert_array_equal(back.w2c, cam.w2c)
    assert (back.width, back.height) == (33, 21)


@pytest.mark.parametrize("change, message", [
    (dict(K=[[0.0, 0, 8], [0, 10, 8], [0, 0, 1]]), "positive focal"),
    (dict(K=[[10.0, 0, 8], [0, -1, 8], [0, 0, 1]]), "positive focal"),
    (dict(w2c=np.diag([1.0, 1.0, 0.0, 1.0])), "not invertible"),
    (dict(w2c=np.diag([2.0, 1.0, 1.0, 1.0])), "proper rotation"),
    (dict(w2c=np.diag([-1.0, 1.0, 1.0, 1.0])), "proper rotation"),
    (dict(width=0), "positive integer"),
    (dict(height=2.5), "positive integer"),
    (dict(K=np.eye(4)), "shape"),
    (dict(w2c=np.full((4, 4), np.nan)), "non-finite"),
])
def test_invalid_cameras_raise_clear_errors(change, message):
    good = dict(K=[[10.0, 0, 8], [0, 10, 8], [0, 0, 1]], w2c=np.eye(4), width=16, height=16)
    with pytest.raises(CameraError, match=message):
        Camera(**(good | change))


def test_look_at_rejects_degenerate_input():
    with pytest.raises(CameraError, match="parallel"):
        look_at([0, 0, 0], [0, 1, 0], [0, 1, 0], 40, 8, 8)
    with pytest.raises(CameraError, match="coincide"):
        look_at([0, 0, 0], [0, 0, 0], [0, 1, 0], 40, 8, 8)
    with pytest.raises(CameraError, match="missing|exactly"):
        Camera.from_dict({"K": np.eye(3).tolist()})


def test_a_cameras_tensors_are_made_once_per_dtype_and_device():
    """``Camera.tensors``: K and w2c as tensors, the same ones on every call for a (dtype, device) (on CUDA a new one is
    a host copy that waits for the GPU, four per rendered frame: NOTES s39), other ones for another dtype; equal to
    the camera's arrays; a pickled or copied camera carries none of them."""
    import copy
    import dataclasses
    import pickle

    cam = Camera(K=[[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]], w2c=np.eye(4), width=64, height=48)
    K, w2c = cam.tensors(torch.float32, "cpu")
    assert cam.tensors(torch.float32, torch.device("cpu"))[0] is K and cam.tensors()[1] is w2c
    K64, _ = cam.tensors(torch.float64, "cpu")
    assert K64 is not K and K64.dtype == torch.float64
    np.testing.assert_array_equal(K64.numpy(), cam.K)
    np.testing.assert_array_equal(w2c.numpy(), cam.w2c.astype(np.float32))
    for other in (pickle.loads(pickle.dumps(cam)), copy.deepcopy(cam), copy.copy(cam), dataclasses.replace(cam)):
        assert other._tensors == {} and other.tensors()[0] is not K
        np.testing.assert_array_equal(other.tensors()[0].numpy(), K.numpy())
    assert len(cam._tensors) == 2  # the original keeps its own
    centre = cam.center_tensor(torch.float64, "cpu")
    assert cam.center_tensor(torch.float64, "cpu") is centre and len(cam._tensors) == 3
    np.testing.assert_allclose(centre.numpy(), cam.center)
    fresh = Camera(K=cam.K, w2c=cam.w2c, width=64, height=48)
    with torch.inference_mode():  # first made under inference mode (an evaluation), then used in training
        fresh.tensors()
    w = torch.ones(3, requires_grad=True)
    (fresh.tensors()[1][:3, :3] @ w).sum().backward()  # inference tensors could not be saved for backward
    assert torch.equal(w.grad, fresh.tensors()[1][:3, :3].sum(0))
