"""A scene in a layout a notebook user easily has (a NumPy array, a (C, H, W) cube, bands last) given to
``Camera.capture``: one InputError naming the layout and the fix, never an AttributeError or a "too small" scene.
Found by a review that used hsicam from Python. Reference: the exact line a user sees, and the capture of the
scene in its (B, C, H, W) layout, which the fix the message names gives back."""

import pytest
import torch

from hsicam.errors import InputError


@pytest.fixture()
def cam_and_scene(tiny_camera):
    cam = tiny_camera()
    c = len(cam.bands)
    side = cam.min_scene_size()[0] + 10
    x = torch.rand((1, c, side, side), generator=torch.Generator().manual_seed(0))
    return cam, x, c


def test_a_numpy_scene_is_told_to_become_a_tensor(cam_and_scene):
    cam, x, _ = cam_and_scene
    with pytest.raises(InputError) as e:
        cam.capture(x.numpy())
    assert str(e.value) == "scene must be a torch.Tensor (B, C, H, W), got ndarray: torch.from_numpy(x)"
    torch.testing.assert_close(cam.capture(torch.from_numpy(x.numpy())), cam.capture(x))


def test_a_cube_with_its_bands_last_is_told_so_not_that_it_is_too_small(cam_and_scene):
    cam, x, c = cam_and_scene
    hwc = x.permute(0, 2, 3, 1).contiguous()  # (1, H, W, C): W = C is far below the camera's minimum size
    with pytest.raises(InputError) as e:
        cam.capture(hwc)
    assert str(e.value) == (f"scene has {hwc.shape[1]} bands but the camera has {c} ({cam.bands!r}); its last axis "
                            "has the camera's bands: a (B, H, W, C) cube is x.permute(0, 3, 1, 2)")
    torch.testing.assert_close(cam.capture(hwc.permute(0, 3, 1, 2)), cam.capture(x))


def test_a_cube_without_its_batch_axis_is_told_to_add_it(cam_and_scene):
    cam, x, _ = cam_and_scene
    with pytest.raises(InputError) as e:
        cam.capture(x[0])
    assert str(e.value) == f"scene must be a (B, C, H, W) tensor, got shape {tuple(x[0].shape)}: a (C, H, W) cube is x[None]"
    torch.testing.assert_close(cam.capture(x[0][None]), cam.capture(x))


def test_a_wrong_band_count_gets_no_layout_hint(cam_and_scene):
    cam, x, c = cam_and_scene
    with pytest.raises(InputError) as e:
        cam.capture(torch.cat([x, x[:, :1]], dim=1))
    assert str(e.value) == f"scene has {c + 1} bands but the camera has {c} ({cam.bands!r})"
