"""Laplacian-preconditioned vertex parameterisation (Nicolet, Jacobson and Jakob 2021, "Large Steps in
Inverse Rendering of Geometry"), on the CPU or a GPU.

Vertices x are optimised through u = (I + λ L) x, L the uniform (combinatorial) graph Laplacian
``L = D − A``: a gradient step on u moves x by the smooth (I + λ L)⁻¹ of the gradient, so a few
silhouette pixels move a whole region rather than single vertices. The solve is the ``largesteps``
package's (sparse Cholesky by ``cholespy``); its matrix builder hard-codes CUDA, so the matrix is
built here, on the vertices' device.
"""

from __future__ import annotations

import numpy as np
import torch


def uniform_laplacian(faces: np.ndarray | torch.Tensor, num_vertices: int,
                      device: torch.device | str = "cpu") -> torch.Tensor:
    """L = D − A of the mesh's edge graph, a coalesced sparse (V, V) float32 tensor."""
    f = torch.as_tensor(np.asarray(faces), dtype=torch.long, device=device)
    edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    edges = torch.cat([edges, edges.flip(1)]).unique(dim=0).T
    size = (num_vertices, num_vertices)
    adjacency = torch.sparse_coo_tensor(edges, torch.ones(edges.shape[1], device=device), size, check_invariants=True)
    index = torch.arange(num_vertices, device=device)
    degree = torch.zeros(num_vertices, device=device).index_add_(0, edges[0], torch.ones(edges.shape[1], device=device))
    diagonal = torch.sparse_coo_tensor(torch.stack([index, index]), degree, size, check_invariants=True)
    return (diagonal - adjacency).coalesce()


class LargeSteps:
    """x ↔ u = (I + λ L) x for one mesh topology; ``vertices(u)`` is differentiable in u."""

    def __init__(self, faces: np.ndarray | torch.Tensor, num_vertices: int, lam: float = 20.0,
                 device: torch.device | str = "cpu"):
        if lam < 0:
            raise ValueError(f"the Laplacian weight must be >= 0, got {lam}")
        index = torch.arange(num_vertices, device=device)
        eye = torch.sparse_coo_tensor(torch.stack([index, index]), torch.ones(num_vertices, device=device),
                                      (num_vertices,) * 2, check_invariants=True)
        self.matrix = (eye + lam * uniform_laplacian(faces, num_vertices, device)).coalesce()
        self._solver = None

    def to_u(self, vertices: torch.Tensor) -> torch.Tensor:
        from largesteps.parameterize import to_differential

        return to_differential(self.matrix, vertices.detach().float())

    def vertices(self, u: torch.Tensor) -> torch.Tensor:
        from largesteps.parameterize import from_differential

        return from_differential(self.matrix, u, "Cholesky")
