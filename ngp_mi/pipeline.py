"""NGP inference: the image formation of the paper (Sec. 3, Eq. "image formation"),

    I = R( G_prop(Π_v(G_shape(z_s)), z_da), L ) ⊕ G_sp^real(Π_v(G_shape(z_s))),

with a handle for every factor: the shape (a latent z_s of a ``train shape`` run, or a user mesh),
the camera v (Π_v is Mitsuba's depth projection), the appearance (a latent z_da, or the code of an
exemplar albedo image through E_da), and the lights L (any number, position and intensity).

:func:`ngp_image` forms one view's image for each variant of the paper (Sec. 5, App. "NGP
variants") and its ablations; :class:`NGP` loads the trained models and renders shapes
(``ngp-mi generate``, :mod:`ngp_mi.commands.generate`, writes images, maps and a report).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ngp_mi.camera import Camera
from ngp_mi.geometry.mesh import TriangleMesh
from ngp_mi.lights import Light, overhead_rig
from ngp_mi.models.maps import MapsModel
from ngp_mi.models.shape import ShapeModel
from ngp_mi.models.specular import SpecularModel
from ngp_mi.render.depth import project_depth
from ngp_mi.render.from_depth import normals_from_depth
from ngp_mi.render.shading import Constants, shade

VARIANTS = ("ngp", "ngp_bp", "ngp_plus", "no_sp", "no_gn", "no_gda")


def latent(seed: int, dim: int) -> torch.Tensor:
    """A latent (z_s or z_da) ~ N(0, I) of one seed: shape k of seed s uses seed s + k, so any one
    can be reproduced alone."""
    return torch.randn(dim, generator=torch.Generator().manual_seed(seed))


def slerp(a: torch.Tensor, b: torch.Tensor, t: float) -> torch.Tensor:
    """Spherical interpolation between latents (linear when they are parallel): it keeps |z| typical
    of a Gaussian sample, where a straight line passes through low-norm latents a GAN never saw."""
    cos = torch.dot(a, b) / (a.norm() * b.norm()).clamp_min(1e-12)
    omega = torch.arccos(cos.clamp(-1.0, 1.0))
    if float(omega) < 1e-6:
        return (1 - t) * a + t * b
    return (torch.sin((1 - t) * omega) * a + torch.sin(t * omega) * b) / torch.sin(omega)


def views_of(camera: Camera, bounds: np.ndarray) -> dict[str, torch.Tensor]:
    """The per-view tensors the map networks read (K, E, NOC bounds), batch of one."""
    return {"K": torch.tensor(camera.K, dtype=torch.float32)[None], "E": torch.tensor(camera.E, dtype=torch.float32)[None],
            "bounds": torch.tensor(np.asarray(bounds), dtype=torch.float32)[None]}


@torch.no_grad()
def ngp_image(maps: MapsModel, specular: SpecularModel | None, depth: torch.Tensor, mask: torch.Tensor,
              camera: Camera, bounds: np.ndarray, z_da: torch.Tensor, lights: Sequence[Light], variant: str = "ngp",
              added_lights: Sequence[Light] = (), constants: Constants | None = None) -> dict[str, torch.Tensor]:
    """One view of NGP from a depth map (1, 1, H, W): the image (linear radiance) and its maps.

    Variants: ``ngp_bp`` R_BP(N^g, I_da^g, L); ``no_sp`` R_diff only (NGP w/o G_sp^real); ``ngp``
    R_diff(L) / π ⊕ G_sp^real(N^g, I_df^g); ``no_gn`` / ``no_gda`` NGP with the depth map's own
    normals / a white albedo (the paper's ablations); ``ngp_plus`` NGP under the overhead rig plus
    R_BP of ``added_lights``. G_sp^real always sees the diffuse image under the training rig (its
    input domain), so its highlights do not follow other lights, as the paper notes. R_* / π is
    radiance (see :mod:`ngp_mi.render.shading`). ``constants`` default to the ones the map networks
    were trained with (``maps.config.constants``; G_sp^real's input is shaded with them too).
    """
    if variant not in VARIANTS:
        raise ValueError(f"NGP variant must be one of {VARIANTS}, got {variant!r}")
    if specular is None and variant in ("ngp", "no_gn", "no_gda", "ngp_plus"):
        raise ValueError(f"variant {variant!r} needs G_sp^real: a `train maps` run with a [specular] stage")
    views = views_of(camera, bounds)
    if variant == "no_gn":
        normal = normals_from_depth(depth, mask, camera)
        albedo_net = maps.G_da(torch.cat([maps.noc(depth, mask, views), normal], 1), z_da)
    else:
        generated = maps.decorate(depth, mask, views, z_da)
        normal, albedo_net = generated["normal"], generated["albedo"]
    albedo = torch.ones_like(albedo_net) if variant == "no_gda" else (albedo_net + 1) / 2
    c = constants or maps.config.constants
    out = {"normal": normal, "albedo": albedo}
    if variant == "ngp_bp":
        out["image"] = shade(normal, albedo, mask, lights, camera, mode="blinn_phong", k_d=c.k_d, k_s=c.k_s,
                             alpha=c.alpha) / math.pi
        return out
    diffuse_lights = overhead_rig() if variant == "ngp_plus" else lights
    image = shade(normal, albedo, mask, diffuse_lights, camera, mode="diffuse", k_d=c.k_d) / math.pi
    if variant != "no_sp":
        base = 2 * maps.render_diffuse(normal, albedo, mask, [camera]) - 1
        out["specular"] = specular.specular(normal, base, mask)
        image = image + out["specular"]
    if variant == "ngp_plus" and added_lights:
        image = image + shade(normal, albedo, mask, added_lights, camera, mode="blinn_phong", k_d=c.k_d, k_s=c.k_s,
                              alpha=c.alpha) / math.pi
    out["image"] = image
    return out


class NGP:
    """The trained generators: G_shape (``shape_run``, optional with user meshes) and the maps and
    G_sp^real (``maps_run``)."""

    def __init__(self, maps_run: str | Path, shape_run: str | Path | None = None):
        self.maps: MapsModel = MapsModel.from_run(maps_run)
        self.specular: SpecularModel | None = SpecularModel.from_run(maps_run)
        self.shape_model: ShapeModel | None = ShapeModel.from_run(shape_run) if shape_run else None

    def shape(self, z_s: torch.Tensor, resolution: int = 64) -> TriangleMesh:
        """G_shape(z_s) as a mesh (coarse-to-fine marching cubes)."""
        if self.shape_model is None:
            raise ValueError("sampling shapes needs a `train shape` run (--shape-run)")
        mesh = self.shape_model.shape(z_s, resolution=resolution).mesh
        if mesh is None:
            raise ValueError("G_shape produced an empty shape for this z_s")
        return mesh

    def appearance(self, seed: int | None = None, exemplar: torch.Tensor | None = None) -> torch.Tensor:
        """z_da: μ(E_da(exemplar albedo (1, 3, H, W) in [0, 1])), or a N(0, I) sample of ``seed``."""
        if exemplar is not None:
            with torch.no_grad():
                return self.maps.E_da(2 * exemplar - 1)[0]
        return latent(seed or 0, self.maps.config.latent_dim)[None]

    def render(self, mesh: TriangleMesh, camera: Camera, z_da: torch.Tensor, lights: Sequence[Light],
               variant: str = "ngp", added_lights: Sequence[Light] = (),
               constants: Constants | None = None) -> dict[str, torch.Tensor]:
        """Π_v of the mesh (Mitsuba), then :func:`ngp_image`; the result includes ``depth`` and ``mask``."""
        projected = project_depth(torch.as_tensor(mesh.vertices, dtype=torch.float32), mesh.faces, camera)
        out = ngp_image(self.maps, self.specular, projected.depth, projected.mask, camera, mesh.bounds, z_da, lights,
                        variant, added_lights, constants)
        return {"depth": projected.depth, "mask": projected.mask, **out}
