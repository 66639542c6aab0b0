"""Inception features for FID / KID, from a local TorchScript file (never downloaded).

FID (Heusel et al. 2017) and KID (Bińkowski et al. 2018) compare the distributions of 2048-d pool3
features of the Inception-v3 network that TensorFlow's FID code uses (the 2015-12-05 graph). We read
it as TorchScript, ``inception-2015-12-05.pt``, the file StyleGAN2-ADA / StyleGAN3 and clean-fid
distribute (NVlabs' metrics weights): TorchScript carries its own architecture and loads without
running Python code, so no network definition is copied here and no weights are fetched. The
module is called as ``model(images_uint8_nchw, return_features=True)`` and resizes to 299² itself.

The distances themselves are :func:`ngp_mi.eval.metrics.fid_from_features` and
:func:`~ngp_mi.eval.metrics.kernel_inception_distance`.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

INCEPTION_FILE = "inception-2015-12-05.pt"


def missing_weights_message(path: str | Path | None) -> str:
    where = f"{path} does not exist; " if path else ""
    return (f"FID / KID need the Inception-v3 weights as a local file: {where}pass --inception-weights "
            f"PATH/{INCEPTION_FILE} (the TorchScript file of NVlabs' StyleGAN2-ADA / StyleGAN3 metrics, also "
            f"used by clean-fid; copy it from a machine that has it — ngp-mi never downloads weights)")


class InceptionFeatures:
    """Pool3 features of sRGB images; ``__call__`` takes (H, W, 3) arrays in [0, 1]."""

    def __init__(self, path: str | Path, batch_size: int = 16, device: str | torch.device = "cpu"):
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(missing_weights_message(path))
        try:
            with warnings.catch_warnings():  # TorchScript is deprecated in torch 2.13 but is the file's format
                warnings.simplefilter("ignore", DeprecationWarning)
                self.model = torch.jit.load(str(path), map_location=device).eval()
        except (RuntimeError, ValueError) as exc:
            raise ValueError(f"{path}: not a TorchScript module ({str(exc).splitlines()[0]}); "
                             + missing_weights_message(None)) from None
        self.path, self.batch_size, self.device = path, batch_size, torch.device(device)

    @torch.no_grad()
    def __call__(self, images: Sequence[np.ndarray]) -> np.ndarray:
        features = []
        for start in range(0, len(images), self.batch_size):
            batch = np.stack([np.clip(image, 0, 1) for image in images[start:start + self.batch_size]])
            x = torch.from_numpy(np.round(batch * 255).astype(np.uint8)).permute(0, 3, 1, 2).to(self.device)
            out = self.model(x, return_features=True)
            features.append(out.reshape(len(batch), -1).double().cpu().numpy())
        return np.concatenate(features)
