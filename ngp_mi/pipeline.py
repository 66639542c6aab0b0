"""NGP inference: the image formation of the paper (Sec. 3, Eq. "image formation"),

    I = R( G_prop(Π_v(G_shape(z_s)), z_da), L ) ⊕ G_sp^real(Π_v(G_shape(z_s))),

with a handle for every factor: the shape (a latent z_s of a ``train shape`` run, or a user mesh),
the camera v (Π_v is Mitsuba's depth projection), the appearance (a latent z_da, or the code of an
exemplar albedo image through E_da), and the lights L (any number, position and intensity).

:func:`ngp_image` forms one view's image for each variant of the paper (Sec. 5, App. "NGP
variants") and its ablations; :class:`NGP` loads the trained models and renders shapes;
``ngp-mi generate`` writes images, the intermediate maps and a report.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ngp_mi.camera import Camera
from ngp_mi.lights import Light, lights_to_json, overhead_rig
from ngp_mi.render.maps import normals_from_depth
from ngp_mi.render.shading import shade

VARIANTS = ("ngp", "ngp_bp", "ngp_plus", "no_sp", "no_gn", "no_gda")


@dataclasses.dataclass(frozen=True)
class Constants:
    """R_BP's constants (App. "Training details": chairs k_d 0.8, k_s 0.2; cars 0.6, 0.4)."""

    k_d: float = 0.8
    k_s: float = 0.2
    alpha: float = 4.0


def views_of(camera: Camera, bounds: np.ndarray) -> dict[str, torch.Tensor]:
    """The per-view tensors the map networks read (K, E, NOC bounds), batch of one."""
    return {"K": torch.tensor(camera.K, dtype=torch.float32)[None], "E": torch.tensor(camera.E, dtype=torch.float32)[None],
            "bounds": torch.tensor(np.asarray(bounds), dtype=torch.float32)[None]}


@torch.no_grad()
def ngp_image(maps: Any, specular: Any, depth: torch.Tensor, mask: torch.Tensor, camera: Camera, bounds: np.ndarray,
              z_da: torch.Tensor, lights: Sequence[Light], variant: str = "ngp", added_lights: Sequence[Light] = (),
              constants: Constants = Constants()) -> dict[str, torch.Tensor]:
    """One view of NGP from a depth map (1, 1, H, W): the image (linear radiance) and its maps.

    Variants: ``ngp_bp`` R_BP(N^g, I_da^g, L); ``no_sp`` R_diff only (NGP w/o G_sp^real); ``ngp``
    R_diff(L) / π ⊕ G_sp^real(N^g, I_df^g); ``no_gn`` / ``no_gda`` NGP with the depth map's own
    normals / a white albedo (the paper's ablations); ``ngp_plus`` NGP under the overhead rig plus
    R_BP of ``added_lights``. G_sp^real always sees the diffuse image under the training rig (its
    input domain), so its highlights do not follow other lights, as the paper notes. R_* / π is
    radiance (see :mod:`ngp_mi.render.shading`).
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
    c = constants
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
        from ngp_mi.eval.maps_eval import load_model, load_specular
        from ngp_mi.train_shape import load_shape_model

        self.maps, self.specular = load_model(maps_run), load_specular(maps_run)
        self.shape_model = load_shape_model(shape_run) if shape_run else None

    def shape(self, z_s: torch.Tensor, resolution: int = 64) -> Any:
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
        generator = torch.Generator().manual_seed(seed or 0)
        return torch.randn(1, self.maps.config.latent_dim, generator=generator)

    def render(self, mesh: Any, camera: Camera, z_da: torch.Tensor, lights: Sequence[Light], variant: str = "ngp",
               added_lights: Sequence[Light] = (), constants: Constants = Constants()) -> dict[str, torch.Tensor]:
        """Π_v of the mesh (Mitsuba), then :func:`ngp_image`; the result includes ``depth`` and ``mask``."""
        from ngp_mi.render.depth import project_depth

        projected = project_depth(torch.as_tensor(mesh.vertices, dtype=torch.float32), mesh.faces, camera)
        out = ngp_image(self.maps, self.specular, projected.depth, projected.mask, camera, mesh.bounds, z_da, lights,
                        variant, added_lights, constants)
        return {"depth": projected.depth, "mask": projected.mask, **out}


def generate(maps_run: str | Path, out: str | Path, shape_run: str | Path | None = None, mesh_path: str | None = None,
             num: int = 4, seed: int = 0, views: Sequence[tuple[float, float]] = ((10.0, -30.0), (10.0, 30.0)),
             resolution: int = 128, lights: Sequence[Light] | None = None, added_lights: Sequence[Light] = (),
             variant: str = "ngp", exemplar: str | None = None, log=print) -> dict[str, Any]:
    """``ngp-mi generate``: ``num`` shapes (z_s of ``seed`` …, or the user's mesh) × ``views`` (θ, φ in
    degrees); writes ``images/*.png``, ``sheet.png`` (depth, normals, albedo, specular, image per
    row), ``generate.json`` and ``report.md``."""
    from ngp_mi.data.datasets import read_image
    from ngp_mi.geometry.loaders import load_mesh
    from ngp_mi.viz import contact_sheet, save_png, to_uint8

    if not mesh_path and not shape_run:
        raise ValueError("generate: give a `train shape` run (--shape-run) to sample shapes, or a --mesh")
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    lights = list(lights) if lights is not None else overhead_rig()
    ngp = NGP(maps_run, shape_run if mesh_path is None else None)
    exemplar_tensor = None
    if exemplar:
        albedo = torch.from_numpy(np.ascontiguousarray(read_image(Path(exemplar), resolution, linear=True)))
        exemplar_tensor = torch.nn.functional.interpolate(albedo.permute(2, 0, 1)[None], size=(resolution, resolution),
                                                          mode="bilinear", align_corners=False)
    shapes = [("mesh", load_mesh(mesh_path))] if mesh_path else []
    for k in range(0 if mesh_path else num):
        z_s = torch.randn(ngp.shape_model.config.z_dim, generator=torch.Generator().manual_seed(seed + k))
        shapes.append((f"z{seed + k}", ngp.shape(z_s)))
    rows, labels, records = [], [], []
    for k, (name, mesh) in enumerate(shapes):
        z_da = ngp.appearance(seed=seed + k, exemplar=exemplar_tensor)
        for theta, phi in views:
            camera = Camera.orbit(theta, phi, resolution)
            result = ngp.render(mesh, camera, z_da, lights, variant, added_lights)
            image = result["image"][0].permute(1, 2, 0).numpy()
            stem = f"{name}_t{theta:g}_p{phi:g}"
            save_png(out / "images" / f"{stem}.png", to_uint8(image))
            records.append({"shape": name, "theta": theta, "phi": phi, "file": f"images/{stem}.png"})
            rows.append(_tiles(result))
            labels.append(stem)
            log(f"generate: {stem}")
    names = ["coarse depth", "normals", "albedo", "specular", "image"]
    sheet = contact_sheet([tile for row in rows for tile in row], [f"{n}" for _ in rows for n in names], columns=len(names))
    save_png(out / "sheet.png", sheet)
    summary = {"maps_run": str(maps_run), "shape_run": str(shape_run) if shape_run else None, "mesh": mesh_path,
               "variant": variant, "resolution": resolution, "lights": json.loads(lights_to_json(lights)),
               "added_lights": json.loads(lights_to_json(added_lights)), "exemplar": exemplar, "images": records}
    (out / "generate.json").write_text(json.dumps(summary, indent=1) + "\n")
    (out / "report.md").write_text(
        f"# NGP images ({variant})\n\nMaps: `{maps_run}`; shapes: {'`' + mesh_path + '`' if mesh_path else f'G_shape of `{shape_run}`, z_s seeds {seed}…{seed + num - 1}'}; "
        f"appearance: {'E_da of `' + exemplar + '`' if exemplar else 'z_da ~ N(0, I), one per shape'}; {len(lights)} "
        f"light(s){f' + {len(added_lights)} added' if added_lights else ''}; {resolution}².\n\n"
        "Rows: one view each (" + ", ".join(labels) + "); columns: " + ", ".join(names) + ".\n\n![sheet](sheet.png)\n")
    return summary


def _tiles(result: dict[str, torch.Tensor]) -> list[np.ndarray]:
    from ngp_mi.viz import to_uint8

    mask = result["mask"][0, 0].numpy() > 0
    depth = result["depth"][0, 0].numpy()
    shown = np.zeros_like(depth)
    if mask.any():
        lo, hi = depth[mask].min(), depth[mask].max()
        shown[mask] = 1 - 0.8 * (depth[mask] - lo) / max(hi - lo, 1e-6)
    to_rgb = lambda t: t[0].permute(1, 2, 0).clamp(0, 1).numpy()  # noqa: E731
    specular = result.get("specular", torch.zeros_like(result["image"]))
    return [to_uint8(np.repeat(shown[..., None], 3, -1), srgb=False),
            to_uint8(((result["normal"] + 1) / 2 * result["mask"])[0].permute(1, 2, 0).clamp(0, 1).numpy(), srgb=False),
            to_uint8(to_rgb(result["albedo"] * result["mask"])), to_uint8(to_rgb(specular)),
            to_uint8(to_rgb(result["image"]))]
