"""Image metrics (PSNR, SSIM, FLIP), full-frame or masked, and distribution distances (FID, KID).

Images are float (H, W, 3). "Linear" metrics take linear radiance; "sRGB" metrics take display
images in [0, 1] (apply ``viz.linear_to_srgb`` first). Masked variants average only over the
object (mask > 0.5). SSIM is scikit-image's (Gaussian window σ = 1.5, as in Wang et al.); FLIP is
NVIDIA's reference implementation (``flip-evaluator``, LDR mode on sRGB images, 67 pixels per
degree).
"""

from __future__ import annotations

import flip_evaluator
import numpy as np
from scipy import linalg
from skimage.metrics import structural_similarity


def _select(error: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    if mask is None:
        return error
    keep = np.asarray(mask) > 0.5
    if not keep.any():
        raise ValueError("metric over an empty mask")
    return error[keep]


def psnr(reference: np.ndarray, test: np.ndarray, mask: np.ndarray | None = None, peak: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(peak² / MSE)``; inf for identical images."""
    mse = float(np.mean(_select((np.asarray(test, np.float64) - reference) ** 2, mask)))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak ** 2 / mse)


def ssim(reference: np.ndarray, test: np.ndarray, mask: np.ndarray | None = None, data_range: float = 1.0) -> float:
    """Mean structural similarity (colour channels averaged), over the mask when given."""
    _, ssim_map = structural_similarity(np.asarray(reference, np.float64), np.asarray(test, np.float64),
                                        channel_axis=-1, data_range=data_range, gaussian_weights=True,
                                        sigma=1.5, use_sample_covariance=False, full=True)
    return float(np.mean(_select(ssim_map.mean(-1), mask)))


def flip(reference_srgb: np.ndarray, test_srgb: np.ndarray, mask: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Mean FLIP error (0 = identical, 1 = maximal) of display images, and the (H, W) error map."""
    error_map, _, _ = flip_evaluator.evaluate(np.clip(reference_srgb, 0, 1).astype(np.float32),
                                              np.clip(test_srgb, 0, 1).astype(np.float32), "LDR",
                                              inputsRGB=True, applyMagma=False, computeMeanError=False)
    error_map = np.asarray(error_map).reshape(reference_srgb.shape[:2])
    return float(np.mean(_select(error_map, mask))), error_map


def added_light_placement(reference: np.ndarray, base: np.ndarray, composite: np.ndarray,
                          mask: np.ndarray | None = None) -> dict[str, float]:
    """Where a layer added to an image puts its light, against what the reference has there (linear
    radiance): with A = max(composite − base, 0) the light added and E = max(reference − base, 0) the
    light the reference has beyond the base image, summed over the object and channels,

    * precision = Σ min(A, E) / Σ A — the share of the added light the reference also has (1: none
      lands where the reference is no brighter than the base);
    * recall = Σ min(A, E) / Σ E — the share of the reference's excess the layer supplies;
    * added = mean A per pixel and channel;
    * colour_deg = the mean angle between the RGB vectors A_p and E_p of a pixel, in degrees,
      weighted by the light they share there, w_p = min(‖A_p‖, ‖E_p‖) (0: the layer's light has the
      hue of the reference's excess wherever both exist, e.g. body-coloured where the reference's
      highlight is; a grey layer on a saturated excess, or multicoloured speckle, scores high).

    An empty sum gives 1 for precision or recall (nothing added, nothing missed) and 0 for
    colour_deg (no shared light, no hue to miss). For NGP the base is R_diff / π and the layer
    G_sp^real ("highlights where the reference has them")."""
    added = np.maximum(_select(np.asarray(composite, np.float64) - base, mask), 0.0)
    excess = np.maximum(_select(np.asarray(reference, np.float64) - base, mask), 0.0)
    matched = float(np.minimum(added, excess).sum())
    total_added, total_excess = float(added.sum()), float(excess.sum())
    return {"precision": matched / total_added if total_added > 0 else 1.0,
            "recall": matched / total_excess if total_excess > 0 else 1.0,
            "added": float(added.mean()),
            "colour_deg": colour_angle_deg(added.reshape(-1, added.shape[-1]), excess.reshape(-1, excess.shape[-1]))}


def colour_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Mean angle (°) between the rows of ``a`` and ``b`` (N, C), weighted by min(‖a_i‖, ‖b_i‖): how
    far the hues of two light layers differ where both have light (0 when they share none)."""
    norm_a, norm_b = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    weight = np.minimum(norm_a, norm_b)
    if not (weight > 0).any():
        return 0.0
    both = weight > 0
    cosine = (a[both] * b[both]).sum(-1) / (norm_a[both] * norm_b[both])
    angle = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
    return float((weight[both] * angle).sum() / weight[both].sum())


def nyquist_power_fraction(image: np.ndarray) -> float:
    """The share of an image's AC power (its per-channel mean removed, summed over channels) at the
    three Nyquist frequencies of its pixel grid, (½, 0), (0, ½) and (½, ½) cycles per pixel: the
    2-pixel stripes and checkerboard of stride-2 transposed convolutions. 1 for a pure checkerboard,
    about 3 / (H W) for white noise, 0 for a flat image and near 0 for a smooth one that fades at the
    borders (sharp edges, and borders that differ, since the DFT wraps, add a little). H and W even."""
    x = np.asarray(image, np.float64)
    x = x.reshape(*x.shape[:2], -1)
    height, width = x.shape[:2]
    if height % 2 or width % 2:
        raise ValueError(f"nyquist_power_fraction: a {height}x{width} image has no Nyquist bin on an odd side")
    power = np.abs(np.fft.fft2(x - x.mean(axis=(0, 1)), axes=(0, 1))) ** 2
    total = float(power.sum())
    nyquist = float(power[[height // 2, 0, height // 2], [0, width // 2, width // 2]].sum())
    return nyquist / total if total > 0 else 0.0


def frechet_distance(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray) -> float:
    """Fréchet distance of two Gaussians, ``|μ1 − μ2|² + tr(Σ1 + Σ2 − 2 (Σ1 Σ2)^½)`` (FID's formula).

    The matrix square root is scipy's; a tiny diagonal offset is added when the product is singular.
    """
    mu1, mu2 = np.atleast_1d(mu1).astype(np.float64), np.atleast_1d(mu2).astype(np.float64)
    sigma1, sigma2 = np.atleast_2d(sigma1).astype(np.float64), np.atleast_2d(sigma2).astype(np.float64)
    covmean = linalg.sqrtm(sigma1 @ sigma2)
    if not np.all(np.isfinite(covmean)):
        offset = np.eye(len(sigma1)) * 1e-6
        covmean = linalg.sqrtm((sigma1 + offset) @ (sigma2 + offset))
    covmean = np.real(covmean)
    diff = mu1 - mu2
    return float(diff @ diff + np.trace(sigma1) + np.trace(sigma2) - 2.0 * np.trace(covmean))


def fid_from_features(features1: np.ndarray, features2: np.ndarray) -> float:
    """FID between two (N, D) feature sets (Inception pool3 features in practice)."""
    return frechet_distance(features1.mean(0), np.cov(features1, rowvar=False),
                            features2.mean(0), np.cov(features2, rowvar=False))


def kernel_inception_distance(features1: np.ndarray, features2: np.ndarray) -> float:
    """KID: unbiased MMD² with the cubic polynomial kernel ``(x·y / d + 1)³`` (Bińkowski et al.)."""
    x, y = np.asarray(features1, np.float64), np.asarray(features2, np.float64)
    d = x.shape[1]
    kxx, kyy, kxy = ((x @ x.T) / d + 1) ** 3, ((y @ y.T) / d + 1) ** 3, ((x @ y.T) / d + 1) ** 3
    m, n = len(x), len(y)
    return float((kxx.sum() - np.trace(kxx)) / (m * (m - 1)) + (kyy.sum() - np.trace(kyy)) / (n * (n - 1))
                 - 2 * kxy.mean())
