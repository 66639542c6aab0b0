import numpy as np
import pytest

from ngp_mi.eval.metrics import (added_light_placement, fid_from_features, flip, frechet_distance, kernel_inception_distance,
                                 nyquist_power_fraction, psnr, ssim)


def test_psnr_known_values_and_mask():
    ref = np.zeros((8, 8, 3))
    test = ref.copy()
    test[:4] = 0.1  # MSE over all = 0.005, over the top half = 0.01
    assert psnr(ref, test) == pytest.approx(10 * np.log10(1 / 0.005))
    mask = np.zeros((8, 8))
    mask[:4] = 1
    assert psnr(ref, test, mask) == pytest.approx(20.0)
    assert psnr(ref, ref) == float("inf")
    with pytest.raises(ValueError, match="empty mask"):
        psnr(ref, test, np.zeros((8, 8)))


def test_ssim_and_flip_order_images_by_degradation():
    rng = np.random.default_rng(0)
    ref = np.clip(rng.uniform(0, 1, (32, 32, 3)), 0, 1)
    slightly, badly = np.clip(ref + rng.normal(0, 0.02, ref.shape), 0, 1), np.clip(ref + rng.normal(0, 0.2, ref.shape), 0, 1)
    assert ssim(ref, ref) == pytest.approx(1.0)
    assert 1.0 > ssim(ref, slightly) > ssim(ref, badly)
    f_same, _ = flip(ref, ref)
    f_slight, error_map = flip(ref, slightly)
    f_bad, _ = flip(ref, badly)
    assert f_same == pytest.approx(0.0, abs=1e-6) and 0 < f_slight < f_bad < 1
    assert error_map.shape == (32, 32)


def test_frechet_distance_against_closed_forms():
    # 1-D Gaussians: (m1 - m2)^2 + (s1 - s2)^2.
    assert frechet_distance(np.array([1.0]), np.array([[4.0]]), np.array([3.0]), np.array([[1.0]])) == pytest.approx(
        (1 - 3) ** 2 + (2 - 1) ** 2)
    # Diagonal covariances: sum over dimensions of the 1-D formula.
    rng = np.random.default_rng(1)
    m1, m2 = rng.normal(size=5), rng.normal(size=5)
    s1, s2 = rng.uniform(0.5, 2, 5), rng.uniform(0.5, 2, 5)
    expected = np.sum((m1 - m2) ** 2 + (s1 - s2) ** 2)
    assert frechet_distance(m1, np.diag(s1 ** 2), m2, np.diag(s2 ** 2)) == pytest.approx(expected)
    # Commuting full covariances (same eigenvectors): an independent computation via eigenvalues.
    q, _ = np.linalg.qr(rng.normal(size=(4, 4)))
    a, b = rng.uniform(0.2, 3, 4), rng.uniform(0.2, 3, 4)
    sig1, sig2 = q @ np.diag(a) @ q.T, q @ np.diag(b) @ q.T
    expected = np.sum((np.sqrt(a) - np.sqrt(b)) ** 2)
    assert frechet_distance(np.zeros(4), sig1, np.zeros(4), sig2) == pytest.approx(expected, rel=1e-8)


def test_fid_and_kid_from_features():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(400, 8))
    same = rng.normal(size=(400, 8))
    shifted = rng.normal(size=(400, 8)) + 1.0
    assert fid_from_features(x, same) < 0.3 < fid_from_features(x, shifted)
    assert abs(kernel_inception_distance(x, same)) < 0.05 < kernel_inception_distance(x, shifted)


def test_added_light_placement_counts_the_light_the_reference_also_has():
    """Base 0.2 everywhere; the reference is brighter by 0.3 on the left half; the layer adds 0.1 on
    the left half and 0.2 on the right: of 0.3 added per row pair, 0.1 is matched."""
    base = np.full((2, 4, 3), 0.2)
    reference, composite = base.copy(), base.copy()
    reference[:, :2] += 0.3
    composite[:, :2] += 0.1
    composite[:, 2:] += 0.2
    place = added_light_placement(reference, base, composite)
    assert place["precision"] == pytest.approx(0.1 / 0.3)
    assert place["recall"] == pytest.approx(0.1 / 0.3)
    assert place["added"] == pytest.approx(0.15)
    mask = np.zeros((2, 4))
    mask[:, :2] = 1  # the left half only: all the added light is the reference's, a third of its excess
    assert added_light_placement(reference, base, composite, mask) == pytest.approx(
        {"precision": 1.0, "recall": 1 / 3, "added": 0.1, "colour_deg": 0.0}, abs=1e-5)  # grey on grey
    nothing = added_light_placement(base, base, base)  # nothing added, nothing missed
    assert nothing == {"precision": 1.0, "recall": 1.0, "added": 0.0, "colour_deg": 0.0}


def test_added_light_colour_is_the_angle_between_the_layers_hues_where_both_have_light():
    """A reference whose excess is pure red: a red layer scores 0°, a grey one arccos(1/√3) = 54.7°
    (the angle of (1, 1, 1) to (1, 0, 0)), a green one 90°; pixels where the reference has no excess
    do not count, and the mean is weighted by the shared light."""
    base = np.zeros((1, 3, 3))
    reference = base.copy()
    reference[0, :2] = [0.4, 0.0, 0.0]  # red excess on two pixels, none on the third
    def colour(layer_pixels):
        composite = base.copy()
        composite[0] = layer_pixels
        return added_light_placement(reference, base, composite)["colour_deg"]
    assert colour([[0.2, 0, 0], [0.3, 0, 0], [0, 0.5, 0]]) == pytest.approx(0.0, abs=1e-5)  # the green one lands off the excess
    assert colour([[0.1, 0.1, 0.1]] * 3) == pytest.approx(np.degrees(np.arccos(1 / np.sqrt(3))))
    # red on pixel 0 (0°, shared light 0.2), green on pixel 1 (90°, shared light 0.1): (0.2·0 + 0.1·90) / 0.3
    assert colour([[0.2, 0, 0], [0, 0.1, 0], [0, 0, 0]]) == pytest.approx(30.0)


def test_nyquist_power_fraction_finds_2_pixel_checkerboards_and_stripes():
    """Pure checkerboards and 2-pixel stripes (any offset and colour) are all Nyquist power; a flat
    image has none and a smooth blob next to none; white noise has its share, 3 of the H W − 1 AC
    frequencies; a faint checkerboard on the blob is found."""
    y, x = np.mgrid[:32, :48]
    checker = ((x + y) % 2)[..., None] * np.array([0.2, 0.5, 0.1]) + 0.3
    assert nyquist_power_fraction(checker) == pytest.approx(1.0)
    assert nyquist_power_fraction(x % 2) == pytest.approx(1.0) and nyquist_power_fraction(y % 2 - 7.0) == pytest.approx(1.0)
    blob = np.exp(-((x - 24) ** 2 + (y - 16) ** 2) / 72.0)[..., None] * np.array([1.0, 0.5, 0.2])
    assert nyquist_power_fraction(blob) < 1e-6
    ramp = x / 48.0  # the DFT wraps it into a saw: its edge puts a little power everywhere
    assert 0 < nyquist_power_fraction(ramp) < 0.01
    assert nyquist_power_fraction(np.full((8, 8, 3), 0.4)) == 0.0
    noise = np.random.default_rng(0).normal(size=(64, 64, 3))
    assert nyquist_power_fraction(noise) == pytest.approx(3 / (64 * 64 - 1), rel=0.5)
    faint = blob + 0.01 * ((x + y) % 2)[..., None]  # a faint checkerboard over the blob: a measurable share
    assert 0.001 < nyquist_power_fraction(faint) < 0.5
    with pytest.raises(ValueError, match="7x8"):
        nyquist_power_fraction(np.zeros((7, 8)))
