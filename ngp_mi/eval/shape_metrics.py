"""Metrics of the shape prior: autoencoder IoU, and coverage / MMD of generated shapes.

Coverage and minimum matching distance follow Achlioptas et al. (2018), as used by IM-NET:
with the Chamfer distance between point clouds sampled on each shape,

* **COV** — the fraction of reference shapes that are the nearest reference of at least one
  generated shape (higher is better: the samples cover the data);
* **MMD** — the mean, over reference shapes, of the distance to their nearest generated shape
  (lower is better: every reference shape has a faithful sample).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch


def chamfer_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Chamfer-L2 between point clouds (..., N, 3) and (..., M, 3).

    ``mean_i min_j |a_i − b_j|² + mean_j min_i |a_i − b_j|²`` (squared distances, as in IM-NET).
    """
    d = torch.cdist(a, b).square()
    return d.min(-1).values.mean(-1) + d.min(-2).values.mean(-1)


def chamfer_matrix(generated: Sequence[np.ndarray], reference: Sequence[np.ndarray]) -> np.ndarray:
    """(G, R) Chamfer distances between every generated and every reference point cloud."""
    ref = torch.as_tensor(np.stack(reference), dtype=torch.float32)
    rows = []
    for g in generated:
        points = torch.as_tensor(g, dtype=torch.float32)[None].expand(len(ref), -1, -1)
        rows.append(chamfer_distance(points, ref))
    return torch.stack(rows).numpy().astype(np.float64)


def coverage_mmd(distances: np.ndarray) -> dict[str, float]:
    """COV and MMD from a (generated, reference) distance matrix."""
    if distances.size == 0:
        raise ValueError("coverage_mmd: empty distance matrix")
    matched = np.unique(distances.argmin(axis=1))
    return {"coverage": float(len(matched) / distances.shape[1]), "mmd": float(distances.min(axis=0).mean())}
