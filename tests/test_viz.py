import numpy as np
from PIL import Image
import pytest

from ngp_mi.viz import contact_sheet, drawable, labelled_grid, linear_to_srgb, save_animation, save_png, to_uint8


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


@pytest.mark.parametrize("size", [32, 64, 128])
def test_captions_wrap_inside_their_tile_at_every_size(size):
    labels = ["NGP-plus (rig + random)", "R_BP on ground-truth maps", "path tracer 1 spp", "NGP-BP_without_spaces_at_all"]
    tiles = [np.full((size, size, 3), 200, np.uint8)] * 4
    sheet = contact_sheet(tiles, labels, columns=4, pad=4)
    below = sheet[4 + size:]  # the caption rows
    for c in range(5):  # every gap between (and beside) the tiles stays background: no caption runs across
        gap = below[:, c * (size + 4):c * (size + 4) + 4]
        assert (gap == 32).all(), (size, c)
    assert (below != 32).any()  # the captions are there


def test_labelled_grid_and_animation(tmp_path):
    tiles = [np.full((16, 16, 3), v, np.uint8) for v in (50, 150, 250)]
    grid = labelled_grid([tiles, tiles], ["shape z0", "shape z1"], ["phi -30", "phi 0", "phi 30"], row_label_width=60)
    assert grid.shape[1] == 60 + 3 * 20 + 4 and (grid[:, 60:] == 250).any()
    with pytest.raises(ValueError, match="need as many labels"):
        labelled_grid([tiles], ["a", "b"], ["x", "y", "z"])
    import imageio.v3 as iio

    path = save_animation(tmp_path / "orbit.gif", tiles, fps=10)
    frames = iio.imread(path)
    assert frames.shape == (3, 16, 16, 3) and list(tmp_path.iterdir()) == [path]


def test_captions_are_set_in_a_font_with_the_symbols_and_spaces():
    from PIL import ImageDraw, ImageFont

    from ngp_mi.viz import caption_font

    font = caption_font()
    assert font is not None and "DejaVu" in font.getname()[0]  # matplotlib's, always installed with it
    assert drawable("Π_v, φ 30°, R_diff ⊕ G_sp") == "Π_v, φ 30°, R_diff ⊕ G_sp"
    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    assert draw.textlength("z_s seed 0", font=font) - draw.textlength("z_sseed0", font=font) >= 5  # visible spaces
    tiles = [np.full((64, 64, 3), 200, np.uint8)]
    assert not np.array_equal(contact_sheet(tiles, ["φ 30°"]), contact_sheet(tiles, ["phi 30°"]))  # drawn, not named
    assert ImageFont.load_default() is not None


def test_symbols_pillows_own_font_lacks_are_written_by_name():
    text = "Π_v, φ 30°, R_diff ⊕ G_sp, μ(E_da), 128², café"
    assert drawable(text, font=None) == "Pi_v, phi 30°, R_diff + G_sp, mu(E_da), 128^2, cafe"
