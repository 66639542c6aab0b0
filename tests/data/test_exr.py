"""OpenEXR I/O: channels, codecs, data windows, bad input."""

import numpy as np
import OpenEXR
import pytest

from ngp_mi.data.exr import COMPRESSIONS, nonzero_windows, read_exr, write_exr


def object_maps(rng, height=40, width=56):
    mask = np.zeros((height, width), np.float32)
    mask[7:29, 11:50] = 1.0
    mask[30, 3] = 1.0  # a stray pixel widens the window
    return {"depth": mask * rng.uniform(1.5, 2.5, mask.shape).astype(np.float32),
            "normal": mask[..., None] * rng.normal(size=(height, width, 3)).astype(np.float32),
            "mask": mask}


@pytest.mark.parametrize("compression", sorted(COMPRESSIONS))
def test_every_codec_is_lossless_with_and_without_a_window(tmp_path, compression):
    maps = object_maps(np.random.default_rng(0))
    (window,) = nonzero_windows(maps["mask"][None])
    assert window == (3, 7, 49, 30)
    for name, kwargs in (("full", {}), ("window", {"window": window})):
        path = write_exr(tmp_path / f"{name}.exr", maps, compression, **kwargs)
        back = read_exr(path)
        assert set(back) == set(maps)
        for channel, array in maps.items():
            np.testing.assert_array_equal(back[channel], array)
    header = OpenEXR.File(str(tmp_path / "window.exr")).header()
    assert [list(c) for c in header["dataWindow"]] == [[3, 7], [49, 30]]
    assert [list(c) for c in header["displayWindow"]] == [[0, 0], [55, 39]]
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_windows_of_a_batch_and_of_an_empty_mask():
    masks = np.zeros((3, 8, 10), np.float32)
    masks[0, 2:4, 5] = 1
    masks[2] = 1
    assert nonzero_windows(masks) == [(5, 2, 5, 3), (0, 0, 0, 0), (0, 0, 9, 7)]


def test_an_empty_image_is_stored_as_one_zero_pixel(tmp_path):
    zeros = {"mask": np.zeros((16, 12), np.float32)}
    path = write_exr(tmp_path / "empty.exr", zeros, "rle", window=nonzero_windows(zeros["mask"][None])[0])
    np.testing.assert_array_equal(read_exr(path)["mask"], zeros["mask"])


def test_a_data_window_reaching_outside_the_display_window_is_clipped(tmp_path):
    """Files written by other tools may store pixels outside the image: read_exr returns the image."""
    stored = np.arange(6 * 8, dtype=np.float32).reshape(6, 8)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "displayWindow": (np.array([0, 0], np.int32), np.array([9, 4], np.int32)),
              "dataWindow": (np.array([-2, 1], np.int32), np.array([5, 6], np.int32))}
    OpenEXR.File(header, {"depth": stored.copy()}).write(str(tmp_path / "outside.exr"))
    depth = read_exr(tmp_path / "outside.exr")["depth"]
    expected = np.zeros((5, 10), np.float32)
    expected[1:5, 0:6] = stored[0:4, 2:8]  # display rows 1..4, columns 0..5
    np.testing.assert_array_equal(depth, expected)


def test_bad_input_is_named(tmp_path):
    maps = object_maps(np.random.default_rng(1))
    with pytest.raises(ValueError, match="compression must be one of"):
        write_exr(tmp_path / "a.exr", maps, "lzw")
    with pytest.raises(ValueError, match=r"window \(0, 0, 56, 10\) is not inside the 56x40 image"):
        write_exr(tmp_path / "a.exr", maps, window=(0, 0, 56, 10))
    with pytest.raises(ValueError, match="'mask' is"):
        write_exr(tmp_path / "a.exr", {"depth": maps["depth"], "mask": maps["mask"][:5]})
    (tmp_path / "torn.exr").write_bytes(b"v/1\x01" + bytes(100))
    with pytest.raises(ValueError, match="torn.exr: not a readable OpenEXR file"):
        read_exr(tmp_path / "torn.exr")
    write_exr(tmp_path / "b.exr", maps)
    with pytest.raises(ValueError, match=r"missing channel\(s\) \['albedo'\]"):
        read_exr(tmp_path / "b.exr", ["depth", "albedo"])
