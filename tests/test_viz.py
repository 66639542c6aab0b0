import numpy as np
import pytest

from ngp_mi.viz import contact_sheet, linear_to_srgb, save_png, to_uint8


def test_srgb_transfer_function_known_values():
    np.testing.assert_allclose(linear_to_srgb(np.array([0.0, 0.0031308, 0.18, 1.0, 2.0])),
                               [0.0, 0.04045, 0.4614, 1.0, 1.0], atol=2e-4)


def test_contact_sheet_and_atomic_png(tmp_path):
    tiles = [to_uint8(np.full((8, 10, 3), v)) for v in (0.1, 0.5, 0.9)]
    sheet = contact_sheet(tiles, ["a", "b", "c"], columns=2, pad=2, label_height=5)
    assert sheet.shape == (2 * (8 + 5 + 2) + 2, 2 * (10 + 2) + 2, 3)
    path = save_png(tmp_path / "x" / "sheet.png", sheet)
    assert path.exists() and list(path.parent.iterdir()) == [path]
    with pytest.raises(ValueError, match="one size"):
        contact_sheet([tiles[0], np.zeros((4, 4, 3), np.uint8)])
