"""Undistortion and resizing: a point projected with distortion lands at its pinhole location."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from vings_core.errors import ConfigError
from vings_core.io.undistort import Undistorter, undistorted_camera, working_size
from vings_core.types import CameraModel

RADTAN = CameraModel(320, 240, 250.0, 255.0, 161.0, 118.0, "radtan",
                     np.array([-0.28, 0.07, 0.0002, 0.00002]))
PINCUSHION = CameraModel(320, 240, 250.0, 250.0, 160.0, 120.0, "radtan", np.array([0.15, 0.02, 0, 0]))
EQUI = CameraModel(320, 240, 160.0, 160.0, 159.5, 119.5, "equidistant",
                   np.array([0.05, -0.02, 0.01, -0.003]))


@pytest.mark.parametrize("cam", [RADTAN, PINCUSHION, EQUI], ids=["radtan", "pincushion", "equidistant"])
@pytest.mark.parametrize("size", [None, (160, 120), (96, 72)])
def test_distorted_point_maps_back_to_pinhole_location(cam, size):
    """3-D points projected WITH distortion into the stored image must appear, after undistortion,
    at their pinhole projection through the delivered camera. Images are coordinate ramps, so each
    output pixel tells which stored-image location it sampled (bilinear is exact on a ramp)."""
    und = Undistorter(cam, *(size or (None, None)))
    out = und.camera
    assert out.distortion_model == "none"
    ys, xs = np.mgrid[0:cam.height, 0:cam.width].astype(np.float32)
    ramp_u, ramp_v = und(xs), und(ys)
    # 3-D points whose pinhole projections through the delivered camera are pixel centres
    rng = np.random.default_rng(1)
    px = np.stack([rng.integers(0, out.width, 300), rng.integers(0, out.height, 300)], 1)
    depth = rng.uniform(0.5, 5.0, (300, 1))
    X = np.concatenate([(px - [out.cx, out.cy]) / [out.fx, out.fy], np.ones((300, 1))], 1) * depth
    z = np.zeros(3)
    if cam.distortion_model == "equidistant":
        src, _ = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), z, z, cam.K, cam.distortion.reshape(4, 1))
    else:
        src, _ = cv2.projectPoints(X, z, z, cam.K, cam.distortion)
    src = src.reshape(-1, 2)   # where the stored (distorted) image shows each point
    got = np.stack([ramp_u[px[:, 1], px[:, 0]], ramp_v[px[:, 1], px[:, 0]]], 1)
    # exact remap: float32 map precision; remap + area shrink: sub-pixel (averaging a curved map)
    tol = 0.05 * cam.width / out.width if und._post_resize else 5e-3
    assert np.abs(got - src).max() < tol


@pytest.mark.parametrize("cam", [RADTAN, PINCUSHION, EQUI], ids=["radtan", "pincushion", "equidistant"])
def test_no_black_border_and_ratio_kept(cam):
    und = Undistorter(cam)
    mx, my = und._maps  # every output pixel samples inside the stored image (no invalid border)
    assert mx.min() >= -1e-3 and mx.max() <= cam.width - 1 + 1e-3
    assert my.min() >= -1e-3 and my.max() <= cam.height - 1 + 1e-3
    # ... and the view is not needlessly narrow: some border pixel samples the image edge
    edge = min(mx.min(), my.min(), cam.width - 1 - mx.max(), cam.height - 1 - my.max())
    assert edge < 0.05
    assert und(np.zeros((cam.height, cam.width), np.uint8)).shape == (cam.height, cam.width)
    c = undistorted_camera(cam)
    assert c.fx / c.fy == pytest.approx(cam.fx / cam.fy)
    assert (c.cx, c.cy) == (cam.cx, cam.cy)


def test_resize_only_scales_intrinsics_and_nearest_keeps_labels():
    cam = CameraModel(640, 480, 500.0, 500.0, 319.5, 239.5)
    und = Undistorter(cam, 320, 240)
    c = und.camera
    assert (c.width, c.height, c.fx, c.cx, c.cy) == (320, 240, 250.0, 159.5, 119.5)
    mask = np.zeros((480, 640), bool)
    mask[100:200, 300:400] = True
    m = und(mask, nearest=True)
    assert m.dtype == bool and m.shape == (240, 320) and m[75, 175] and not m[10, 10]
    depth = np.where(mask, 2.5, 1.0).astype(np.float32)
    assert set(np.unique(und(depth, nearest=True)).tolist()) == {1.0, 2.5}
    # nearest sampling follows the pixel centres (output j <- source 2 j + 0.5, a tie between
    # 2 j and 2 j + 1), not floor(2 j): a one-pixel stripe at odd source columns is kept
    stripes = np.zeros((480, 640), np.uint8)
    stripes[:, 1::2] = 1
    assert und(stripes, nearest=True).min() == 1
    same = Undistorter(cam)
    img = np.ones((480, 640), np.uint8)
    assert same.is_identity and same(img) is img


def test_undistort_false_keeps_model():
    und = Undistorter(RADTAN, 160, 120, undistort=False)
    assert und.camera.distortion_model == "radtan" and und.camera.fx == pytest.approx(125.0)


def test_working_size():
    assert working_size(752, 480, None, None) == (752, 480)
    assert working_size(752, 480, 376, None) == (376, 240)
    assert working_size(752, 480, None, 240) == (376, 240)
    assert working_size(752, 480, 100, 100) == (100, 100)
    with pytest.raises(ConfigError, match="width must be positive"):
        working_size(752, 480, 0, None)
