"""Image codec: raw sensor_msgs/Image buffers and compressed images <-> arrays."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from vings_core.errors import InputError
from vings_core.io.image_codec import (FrameConverter, decode_compressed, decode_image, encode_image,
                                       read_image_file)

rng = np.random.default_rng(0)


@pytest.mark.parametrize("arr,enc", [
    (rng.integers(0, 256, (7, 5), dtype=np.uint8), "mono8"),
    (rng.integers(0, 256, (7, 5, 3), dtype=np.uint8), "rgb8"),
    (rng.integers(0, 256, (7, 5, 4), dtype=np.uint8), "rgba8"),
    (rng.integers(0, 65536, (7, 5), dtype=np.uint16), "16UC1"),
    (rng.integers(0, 65536, (7, 5, 3), dtype=np.uint16), "rgb16"),
    (rng.standard_normal((7, 5)).astype(np.float32), "32FC1"),
])
def test_encode_decode_round_trip(arr, enc):
    e, step, data = encode_image(arr)
    assert e == enc
    assert step == arr.shape[1] * (arr.shape[2] if arr.ndim == 3 else 1) * arr.itemsize
    out = decode_image(data, e, arr.shape[1], arr.shape[0], step)
    expect = arr[..., :3] if enc == "rgba8" else arr  # alpha is dropped on decode
    assert out.dtype == arr.dtype and np.array_equal(out, expect)


def test_bgr_and_bgra_come_back_rgb():
    rgb = rng.integers(0, 256, (4, 6, 3), dtype=np.uint8)
    out = decode_image(rgb[..., ::-1].tobytes(), "bgr8", 6, 4, 18)
    assert np.array_equal(out, rgb)
    bgra = np.concatenate([rgb[..., ::-1], np.full((4, 6, 1), 9, np.uint8)], 2)
    assert np.array_equal(decode_image(bgra.tobytes(), "bgra8", 6, 4, 24), rgb)


def test_step_padding_and_big_endian():
    a = rng.integers(0, 65536, (3, 4), dtype=np.uint16)
    be = a.astype(">u2").tobytes()
    padded = b"".join(be[r * 8:(r + 1) * 8] + b"\xff\xff" for r in range(3))  # step 10 > 8
    out = decode_image(padded, "16UC1", 4, 3, 10, is_bigendian=True)
    assert np.array_equal(out, a) and out.dtype == np.uint16
    m = rng.integers(0, 256, (3, 5), dtype=np.uint8)
    pad = np.concatenate([m, np.zeros((3, 3), np.uint8)], 1)
    assert np.array_equal(decode_image(pad.tobytes(), "mono8", 5, 3, 8), m)


def test_bayer_and_yuv_give_rgb():
    color = np.array([200, 100, 50], np.uint8)  # R, G, B
    mosaic = np.zeros((8, 8), np.uint8)
    mosaic[0::2, 0::2] = color[0]   # R at (0, 0): rggb
    mosaic[0::2, 1::2] = color[1]
    mosaic[1::2, 0::2] = color[1]
    mosaic[1::2, 1::2] = color[2]
    out = decode_image(mosaic.tobytes(), "bayer_rggb8", 8, 8, 8)
    assert out.shape == (8, 8, 3)
    assert np.abs(out[3:5, 3:5].astype(int) - color.astype(int)).max() <= 2
    uyvy = np.tile(np.array([128, 180, 128, 180], np.uint8), 8).reshape(2, 16)  # neutral, Y = 180
    out = decode_image(uyvy.tobytes(), "uyvy", 8, 2, 16)
    # BT.601 limited range: (180 - 16) * 255 / 219 = 191, equal in R, G and B
    assert out.shape == (2, 8, 3) and np.abs(out.astype(int) - 191).max() <= 1


def test_decode_errors_name_the_problem():
    with pytest.raises(InputError, match=r"topic /x.*unknown image encoding 'nv12'"):
        decode_image(b"\0" * 10, "nv12", 2, 2, 2, where="topic /x")
    with pytest.raises(InputError, match=r"cam: image data has 5 bytes, expected 12"):
        decode_image(b"\0" * 5, "mono8", 4, 3, 4, where="cam")
    with pytest.raises(InputError, match="more than step"):
        decode_image(b"\0" * 13, "mono8", 4, 3, 4)
    with pytest.raises(InputError, match="shorter than one row"):
        decode_image(b"\0" * 12, "rgb8", 4, 1, 6)
    with pytest.raises(InputError, match="cannot encode"):
        encode_image(np.zeros((2, 2, 2), np.uint8))


@pytest.mark.parametrize("ext", ["jpg", "png"])
def test_compressed_round_trip(ext):
    rgb = np.zeros((16, 24, 3), np.uint8)
    rgb[..., 0] = 220  # red
    rgb[4:8, 4:8] = [10, 200, 30]
    ok, buf = cv2.imencode("." + ext, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    out = decode_compressed(buf.tobytes(), "rgb8; %s compressed bgr8" % ext, "t")
    err = np.abs(out.astype(int) - rgb.astype(int))
    assert out.shape == rgb.shape
    if ext == "png":
        assert err.max() == 0
    else:  # lossy: colour right away from the block edges, small mean error
        assert err.mean() < 6 and np.abs(out[12, 20].astype(int) - [220, 0, 0]).max() <= 8
    gray = np.arange(64, dtype=np.uint8).reshape(8, 8)
    ok, buf = cv2.imencode(".png", gray)
    assert np.array_equal(decode_compressed(buf, "png"), gray)


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_compressed_bayer_is_demosaiced_like_a_raw_image(pattern):
    """compressed_image_transport compresses a Bayer image as the raw mosaic and says so in the
    format ("bayer_rggb8; png compressed "): it must come back RGB, as from a raw Image."""
    color = {"r": 200, "g": 100, "b": 30}
    mosaic = np.zeros((8, 10), np.uint8)
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        mosaic[dy::2, dx::2] = color[pattern[k]]
    ok, buf = cv2.imencode(".png", mosaic)
    out = decode_compressed(buf.tobytes(), f"bayer_{pattern}8; png compressed ", "cam")
    raw = decode_image(mosaic.tobytes(), f"bayer_{pattern}8", 10, 8, 10)
    assert out.shape == (8, 10, 3) and np.array_equal(out, raw)
    assert np.abs(out[3:5, 3:5].astype(int) - [200, 100, 30]).max() <= 2
    # a colour stream that claims to be Bayer is an error, not a silently wrong image
    ok, buf = cv2.imencode(".png", np.zeros((8, 10, 3), np.uint8))
    with pytest.raises(InputError, match="cam: a bayer_rggb8 compressed image must decode to one channel"):
        decode_compressed(buf.tobytes(), "bayer_rggb8; png compressed ", "cam")


def test_corrupt_compressed_and_files(tmp_path):
    with pytest.raises(InputError, match=r"/cam/c @ 5: corrupt compressed image"):
        decode_compressed(b"\xff\xd8 not a jpeg", "jpeg", "/cam/c @ 5")
    with pytest.raises(InputError, match="empty"):
        decode_compressed(b"", "jpeg", "x")
    with pytest.raises(InputError, match="compressedDepth"):
        decode_compressed(b"abc", "16UC1; compressedDepth", "x")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG garbage")
    with pytest.raises(InputError, match=r"bad.png: corrupt or unreadable"):
        read_image_file(bad)
    with pytest.raises(InputError, match="image file not found"):
        read_image_file(tmp_path / "nope.png")


def test_frame_converter_fixed_mapping():
    notes = []
    conv = FrameConverter("src", notes.append)
    twelve_bit = np.array([[0, 4095], [2048, 16]], np.uint16)
    out = conv(twelve_bit)
    assert out.dtype == np.uint8 and out[0, 1] == 255 and out[1, 0] == 128
    assert np.array_equal(conv(np.array([[4095]], np.uint16)), [[255]])  # same shift afterwards
    assert len(notes) == 1 and "shift of 4 bits" in notes[0]
    fconv = FrameConverter("f", notes.append)
    assert np.array_equal(fconv(np.array([[0.0, 1.0, 0.5]], np.float32)), [[0, 255, 128]])
    u8 = np.array([[3]], np.uint8)
    assert FrameConverter("u")(u8) is u8


def test_frame_converter_skips_black_first_frames_and_reports_saturation():
    notes = []
    conv = FrameConverter("src", notes.append)
    assert np.array_equal(conv(np.zeros((2, 2), np.uint16)), np.zeros((2, 2), np.uint8))  # dark start
    assert not notes                                       # the mapping is not fixed by it
    out = conv(np.array([[3000, 1500]], np.uint16))        # 12-bit values: shift 4
    assert out.tolist() == [[187, 93]] and "shift of 4 bits" in notes[-1]
    conv(np.array([[65535]], np.uint16))                   # brighter than the mapping: saturates
    conv(np.array([[65535]], np.uint16))
    assert sum("saturate" in n for n in notes) == 1        # reported once
    # a dim first image of a 12-bit camera (max 600: 10 bits) leaves headroom up to 1023
    dim = FrameConverter("dim", notes.append)
    assert dim(np.array([[600, 300]], np.uint16)).tolist() == [[150, 75]] and "shift of 2 bits" in notes[-1]
    assert dim(np.array([[1023]], np.uint16)).tolist() == [[255]]
    fconv = FrameConverter("f", notes.append)
    assert fconv(np.zeros((1, 2), np.float32)).tolist() == [[0, 0]]
    assert fconv(np.array([[50.0, 25.0]], np.float32)).tolist() == [[255, 128]]


def test_odd_width_yuv_and_bayer_are_input_errors():
    with pytest.raises(InputError, match="even width"):
        decode_image(np.zeros(12, np.uint8).tobytes(), "yuv422", 3, 2, 6, "cam")
    with pytest.raises(InputError, match="even width and height"):
        decode_image(np.zeros(12, np.uint8).tobytes(), "bayer_rggb8", 4, 3, 4, "cam")
