"""NGP inference: the image formation of the paper (Sec. 3, Eq. "image formation"),

    I = R( G_prop(Π_v(G_shape(z_s)), z_da), L ) ⊕ G_sp^real(Π_v(G_shape(z_s))),

with a handle for every factor: the shape (a latent z_s of a ``train shape`` run, or a user mesh),
the camera v (Π_v is Mitsuba's depth projection), the appearance (a latent z_da, or the code of an
exemplar albedo image through E_da), and the lights L (any number, position and intensity).

:func:`ngp_image` forms one view's image for each variant of the paper (Sec. 5, App. "NGP
variants") and its ablations. The stage functions keep autograd on, so a fit can differentiate an
image through every network and Π_v (``ngp-mi fit-shape``); :class:`NGP` and :class:`NGPScene`
render without it; :class:`NGP` loads the trained models and renders shapes
(``ngp-mi generate``, :mod:`ngp_mi.commands.generate`, writes images, maps and a report).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import BinaryIO, Sequence

import numpy as np
import torch

from ngp_mi.camera import PAPER_FOCAL_MM, PAPER_RADIUS, Camera
from ngp_mi.data.datasets import ReflectanceMapDataset, read_image
from ngp_mi.geometry.mesh import TriangleMesh
from ngp_mi.lights import Light, overhead_rig
from ngp_mi.models.maps import DEPTH_CENTER, MapsModel, depth_to_net
from ngp_mi.models.pretrained import load_model
from ngp_mi.models.shape import ShapeModel
from ngp_mi.models.specular import SpecularModel, add_specular
from ngp_mi.nets.networks import check_image_size
from ngp_mi.render.depth import project_depth
from ngp_mi.render.from_depth import normals_from_depth
from ngp_mi.render.shading import Constants, shade
from ngp_mi.viz import chw_to_uint8, depth_to_uint8

VARIANTS = ("ngp", "ngp_bp", "ngp_plus", "no_sp", "no_gn", "no_gda")
NEEDS_SPECULAR = ("ngp", "ngp_plus", "no_gn", "no_gda")  # the variants that blend G_sp^real


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


def as_latent(value: torch.Tensor | int, dim: int, name: str = "a latent") -> torch.Tensor:
    """A latent (``dim``,) given as a seed (:func:`latent`) or as a vector."""
    z = latent(value, dim) if isinstance(value, int) else torch.as_tensor(value, dtype=torch.float32).reshape(-1)
    if z.shape != (dim,):
        raise ValueError(f"{name} must have {dim} entries, got {tuple(z.shape)}")
    return z


def exemplar_image(source: str | Path | BinaryIO, resolution: int) -> torch.Tensor:
    """An exemplar albedo image (a file, or an open one such as an upload) as a linear (1, 3, R, R) tensor."""
    albedo = torch.from_numpy(np.ascontiguousarray(read_image(source, resolution, linear=True)))
    return torch.nn.functional.interpolate(albedo.permute(2, 0, 1)[None], size=(resolution, resolution),
                                           mode="bilinear", align_corners=False)


def display_maps(result: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """uint8 (H, W, 3) pictures of a render's maps (:meth:`NGPScene.render` with ``maps``): coarse
    depth, normals, albedo, the shaded image before the blend (``shaded``, when present), the specular
    map (black without one) and the image; colours in sRGB, normals and depth as they are."""
    mask = result["mask"]
    shown = {"depth": depth_to_uint8(result["depth"][0, 0], mask[0, 0]),
             "normal": chw_to_uint8((result["normal"] + 1) / 2 * mask, srgb=False),
             "albedo": chw_to_uint8(result["albedo"] * mask),
             "specular": chw_to_uint8(result.get("specular", torch.zeros_like(result["image"]))),
             "image": chw_to_uint8(result["image"])}
    if "shaded" in result:
        shown["shaded"] = chw_to_uint8(result["shaded"])
    return shown


def views_of(camera: Camera, bounds: np.ndarray) -> dict[str, torch.Tensor]:
    """The per-view tensors the map networks read (K, E, NOC bounds), batch of one."""
    return {"K": torch.tensor(camera.K, dtype=torch.float32)[None], "E": torch.tensor(camera.E, dtype=torch.float32)[None],
            "bounds": torch.tensor(np.asarray(bounds), dtype=torch.float32)[None]}


def _check_variant(variant: str, specular: SpecularModel | None) -> None:
    if variant not in VARIANTS:
        raise ValueError(f"NGP variant must be one of {VARIANTS}, got {variant!r}")
    if specular is None and variant in NEEDS_SPECULAR:
        raise ValueError(f"variant {variant!r} needs G_sp^real: a `train maps` run with a [specular] stage")


def at_training_distance(depth: torch.Tensor, mask: torch.Tensor, camera: Camera) -> torch.Tensor:
    """The depth map moved along the optical axis so the world origin (the object's centre) lies at
    the distance the map networks were trained at (``DEPTH_CENTER``, the paper's ρ = 2): a camera
    moved nearer or farther changes the object's size in the image, not the depth range G_n reads."""
    offset = float(camera.t[2]) - DEPTH_CENTER
    return depth - offset * mask if offset else depth


def generate_normals(maps: MapsModel, depth: torch.Tensor, mask: torch.Tensor, camera: Camera,
                     variant: str = "ngp") -> torch.Tensor:
    """N^g = G_n(d) (paper Eq. image formation), or the depth map's own normals (ablation ``no_gn``)."""
    if variant == "no_gn":
        return normals_from_depth(depth, mask, camera)
    own = normals_from_depth(depth, mask, camera) if maps.uses_own_normals else None
    return maps.generate_normals(depth_to_net(at_training_distance(depth, mask, camera), mask), [camera], own)


def generate_albedo(maps: MapsModel, depth: torch.Tensor, mask: torch.Tensor, camera: Camera, bounds: np.ndarray,
                    normal: torch.Tensor, z_da: torch.Tensor, variant: str = "ngp") -> torch.Tensor:
    """I_da^g = G_da(NOC(d), N^g, z_da) in [0, 1] (paper Eq. image formation), or white (ablation ``no_gda``)."""
    if variant == "no_gda":
        return torch.ones_like(normal)
    return (maps.G_da(albedo_condition(maps, depth, mask, camera, bounds, normal), z_da) + 1) / 2


def albedo_condition(maps: MapsModel, depth: torch.Tensor, mask: torch.Tensor, camera: Camera, bounds: np.ndarray,
                     normal: torch.Tensor) -> torch.Tensor:
    """G_da's condition, NOC(d) beside N^g (the part of its input that does not depend on z_da)."""
    return maps.albedo_condition(maps.noc(depth, mask, views_of(camera, bounds)), normal)


@dataclasses.dataclass(frozen=True)
class ExemplarView:
    """An exemplar albedo map with the geometry it was seen on — what :func:`fit_appearance` reads:
    ``albedo`` (1, 3, H, W) in [0, 1], ``depth`` and ``mask`` (1, 1, H, W) of the same view, its
    ``camera`` and the object's ``bounds`` (for the NOC)."""
    albedo: torch.Tensor
    depth: torch.Tensor
    mask: torch.Tensor
    camera: Camera
    bounds: np.ndarray

    def __post_init__(self) -> None:
        h, w = self.camera.height, self.camera.width
        for name, channels in (("albedo", 3), ("depth", 1), ("mask", 1)):
            if tuple(getattr(self, name).shape) != (1, channels, h, w):
                raise ValueError(f"ExemplarView: {name} must be (1, {channels}, {h}, {w}) for its camera, "
                                 f"got {tuple(getattr(self, name).shape)}")
        if float(self.mask.sum()) == 0:
            raise ValueError("ExemplarView: the mask holds no object pixel; there is no albedo to fit")

    @classmethod
    def from_dataset(cls, root: str | Path, item: int = 0) -> "ExemplarView":
        """View ``item`` (in the manifest's (shape, view) order) of a ``render-dataset`` folder rendered
        with the albedo, depth and mask channels: the true albedo map with its own geometry."""
        dataset = ReflectanceMapDataset(root, ("albedo", "depth", "mask"))
        if not 0 <= item < len(dataset):
            raise ValueError(f"{root}: exemplar item {item} is out of range; the folder has {len(dataset)} views")
        view = dataset[item]
        h, w = view["depth"].shape[-2:]
        camera = Camera.from_K_E(view["K"].numpy(), view["E"].numpy(), w, h)
        return cls(view["albedo"][None], view["depth"][None], view["mask"][None], camera, view["bounds"].numpy())


def fit_appearance(maps: MapsModel, exemplar: torch.Tensor, depth: torch.Tensor, mask: torch.Tensor, camera: Camera,
                   bounds: np.ndarray, steps: int, lr: float = 0.05) -> torch.Tensor:
    """z_da for an exemplar albedo map ``exemplar`` (1, 3, H, W) in [0, 1] seen on its own geometry
    (``depth``, ``mask``, ``camera``): μ(E_da(exemplar)), the paper's encoder, refined by ``steps`` Adam
    steps on the L1 over the object between G_da(NOC(d), N^g, z_da) and the exemplar
    (encoder-initialised GAN inversion, beyond the paper; ``steps = 0`` returns μ). G_da's weights
    stay fixed, so z_da can only pick appearances G_da can paint: it corrects the encoder's colours,
    which cost NGP's image most of its FLIP over the true maps (bench/RESULTS.md)."""
    with torch.no_grad():
        z_da = maps.E_da(2 * exemplar - 1)[0]
        if steps <= 0:
            return z_da
        condition = albedo_condition(maps, depth, mask, camera, bounds, generate_normals(maps, depth, mask, camera))
    z_da = z_da.detach().clone().requires_grad_(True)
    optimiser = torch.optim.Adam([z_da], lr=lr)
    area = mask.sum().clamp_min(1.0) * exemplar.shape[1]
    for _ in range(steps):
        albedo = (maps.G_da(condition, z_da) + 1) / 2
        loss = ((albedo - exemplar).abs() * mask).sum() / area
        (grad,) = torch.autograd.grad(loss, z_da)  # G_da's weights take no gradient
        z_da.grad = grad
        optimiser.step()
    return z_da.detach()


def realistic_specular(maps: MapsModel, specular: SpecularModel, normal: torch.Tensor, albedo: torch.Tensor,
                       mask: torch.Tensor, camera: Camera) -> torch.Tensor:
    """G_sp^real(N^g, I_df^g): the learned specular map, from the diffuse image under the training rig
    (its input domain; its highlights do not follow other lights, as the paper notes)."""
    base = 2 * maps.render_diffuse(normal, albedo, mask, [camera]) - 1
    return specular.specular(normal, base, mask, specular.highlight(maps, normal, mask, [camera]))


def shade_maps(normal: torch.Tensor, albedo: torch.Tensor, mask: torch.Tensor, depth: torch.Tensor, camera: Camera,
               lights: Sequence[Light], variant: str, constants: Constants,
               added_lights: Sequence[Light] = ()) -> torch.Tensor:
    """The fixed renderer of the variant, as radiance (R / π): R_BP(L) for ``ngp_bp``; R_diff(L) for
    NGP and its ablations; R_diff(rig) + R_BP(added lights) for ``ngp_plus``. ``depth`` places the
    surface for point lights."""
    c = constants
    if variant == "ngp_bp":
        return shade(normal, albedo, mask, lights, camera, mode="blinn_phong", k_d=c.k_d, k_s=c.k_s,
                     alpha=c.alpha, depth=depth) / math.pi
    image = shade(normal, albedo, mask, overhead_rig() if variant == "ngp_plus" else lights, camera, mode="diffuse",
                  k_d=c.diffuse_k_d, depth=depth) / math.pi
    if variant == "ngp_plus" and added_lights:
        image = image + shade(normal, albedo, mask, added_lights, camera, mode="blinn_phong", k_d=c.k_d, k_s=c.k_s,
                              alpha=c.alpha, depth=depth) / math.pi
    return image


def ngp_image(maps: MapsModel, specular: SpecularModel | None, depth: torch.Tensor, mask: torch.Tensor,
              camera: Camera, bounds: np.ndarray, z_da: torch.Tensor, lights: Sequence[Light], variant: str = "ngp",
              added_lights: Sequence[Light] = (), constants: Constants | None = None) -> dict[str, torch.Tensor]:
    """One view of NGP from a depth map (1, 1, H, W): the image (linear radiance) and its maps.

    Variants: ``ngp_bp`` R_BP(N^g, I_da^g, L); ``no_sp`` R_diff only (NGP w/o G_sp^real); ``ngp``
    R_diff(L) / π ⊕ G_sp^real(N^g, I_df^g); ``no_gn`` / ``no_gda`` NGP with the depth map's own
    normals / a white albedo (the paper's ablations); ``ngp_plus`` NGP under the overhead rig plus
    R_BP of ``added_lights``. R_* / π is radiance (see :mod:`ngp_mi.render.shading`). ``constants``
    default to the ones the map networks were trained with (``maps.config.constants``; G_sp^real's
    input is shaded with them too). The stages are the functions above; :class:`NGPScene` caches them.
    """
    _check_variant(variant, specular)
    normal = generate_normals(maps, depth, mask, camera, variant)
    albedo = generate_albedo(maps, depth, mask, camera, bounds, normal, z_da, variant)
    out = {"normal": normal, "albedo": albedo}
    image = shade_maps(normal, albedo, mask, depth, camera, lights, variant, constants or maps.config.constants,
                       added_lights)
    if variant in NEEDS_SPECULAR:
        out["specular"] = realistic_specular(maps, specular, normal, albedo, mask, camera)
        image = add_specular(image, out["specular"])
    out["image"] = image
    return out


class EmptyShape(ValueError):
    """G_shape's field has no inside for this latent: there is nothing to render."""


class NGP:
    """The trained generators: G_shape (``shape_run``, optional with user meshes) and the maps and
    G_sp^real (``maps_run``)."""

    def __init__(self, maps_run: str | Path, shape_run: str | Path | None = None):
        self.maps: MapsModel = MapsModel.from_run(maps_run)
        self.specular: SpecularModel | None = SpecularModel.from_run(maps_run)
        self.shape_model: ShapeModel | None = ShapeModel.from_run(shape_run) if shape_run else None
        self.card: dict | None = None  # a shipped model's card

    @classmethod
    def pretrained(cls, name_or_path: str | Path) -> "NGP":
        """A shipped model (``chair``, ``car``) or a model folder written by ``ngp-mi export-model``."""
        maps, specular, shape_model, card = load_model(name_or_path)
        ngp = cls.of(maps, specular, shape_model)
        ngp.card = card
        return ngp

    @classmethod
    def of(cls, maps: MapsModel, specular: SpecularModel | None = None, shape_model: ShapeModel | None = None) -> "NGP":
        """From models in memory (just trained, or built for a benchmark); they are put in eval mode."""
        ngp = cls.__new__(cls)
        ngp.maps, ngp.specular, ngp.shape_model = maps.eval(), specular and specular.eval(), shape_model
        ngp.card = None
        if shape_model is not None:
            shape_model.eval()
        return ngp

    def shape(self, z_s: torch.Tensor, resolution: int = 64) -> TriangleMesh:
        """G_shape(z_s) as a mesh (coarse-to-fine marching cubes)."""
        if self.shape_model is None:
            raise ValueError("sampling shapes needs a `train shape` run (--shape-run)")
        mesh = self.shape_model.shape(z_s, resolution=resolution).mesh
        if mesh is None:
            raise EmptyShape("G_shape produced an empty shape for this z_s")
        return mesh

    def appearance(self, seed: int | None = None, exemplar: torch.Tensor | None = None,
                   view: ExemplarView | None = None, fit_steps: int = 30) -> torch.Tensor:
        """z_da: μ(E_da(exemplar albedo (1, 3, H, W) in [0, 1])); for an exemplar ``view`` with its
        geometry, that code refined by ``fit_steps`` steps on G_da's L1 to it (:func:`fit_appearance`);
        or a N(0, I) sample of ``seed``."""
        if view is not None:
            return fit_appearance(self.maps, view.albedo, view.depth, view.mask, view.camera, view.bounds, fit_steps)
        if exemplar is not None:
            with torch.no_grad():
                return self.maps.E_da(2 * exemplar - 1)[0]
        return latent(seed or 0, self.maps.config.latent_dim)[None]

    @torch.no_grad()
    def render(self, mesh: TriangleMesh, camera: Camera, z_da: torch.Tensor, lights: Sequence[Light],
               variant: str = "ngp", added_lights: Sequence[Light] = (),
               constants: Constants | None = None) -> dict[str, torch.Tensor]:
        """Π_v of the mesh (Mitsuba), then :func:`ngp_image`; the result includes ``depth`` and ``mask``."""
        projected = project_depth(torch.as_tensor(mesh.vertices, dtype=torch.float32), mesh.faces, camera)
        out = ngp_image(self.maps, self.specular, projected.depth, projected.mask, camera, mesh.bounds, z_da, lights,
                        variant, added_lights, constants)
        return {"depth": projected.depth, "mask": projected.mask, **out}


STAGES = ("extract", "project", "normals", "albedo", "specular", "shade", "blend")


def _same(a: object, b: object) -> bool:
    """Whether a handle's new value equals its old one (tensors and arrays by value, meshes by identity)."""
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        return a.shape == b.shape and bool(torch.equal(a, b))
    if isinstance(a, Camera) and isinstance(b, Camera):
        return a.to_dict() == b.to_dict()
    if isinstance(a, TriangleMesh) or isinstance(b, TriangleMesh):
        return a is b
    try:
        return bool(a == b)
    except (TypeError, ValueError):
        return False


class NGPScene:
    """NGP driven like a renderer: set the handles, call :meth:`render`.

    Handles (paper Sec. 3.1): the shape (z_s by seed or vector, a slerp between two, a user or
    edited mesh), the camera (θ, φ, distance, focal length, or any :class:`Camera`), the appearance
    (z_da by seed or vector, a slerp, an exemplar albedo image through E_da, or an edited albedo map
    used directly), the lights (any number of directional and point lights; the overhead rig by
    default), the variant and the Blinn-Phong constants.

    Each stage of the data flow keeps its result until one of its inputs changes (``../DESIGN.md``):

    ========  =========================================  ==========================
    stage     computes                                   re-runs after a change of
    ========  =========================================  ==========================
    extract   G_shape(z_s) → mesh                        shape
    project   Π_v(mesh) → depth, mask (Mitsuba)          + camera
    normals   G_n(d)                                     + variant's normals
    albedo    G_da(NOC, N, z_da) or the edited map       + appearance
    specular  G_sp^real(N, I_df)                         (as albedo; only variants that blend it)
    shade     R_diff / R_BP under the lights             + lights, variant, constants
    blend     shade ⊕ specular                           any of the above
    ========  =========================================  ==========================

    ``stage_runs`` counts how often each stage ran, so a light change can be seen to re-run only
    shade and blend.
    """

    def __init__(self, ngp: NGP, resolution: int = 128, variant: str = "ngp"):
        self.ngp = ngp
        self.resolution = resolution
        self.stage_runs: dict[str, int] = {stage: 0 for stage in STAGES}
        self._versions = {"shape": 0, "camera": 0, "appearance": 0, "lights": 0, "variant": 0, "constants": 0}
        self._cache: dict[str, tuple[tuple, object]] = {}
        self._shape: tuple[str, object] | None = None
        self.camera = Camera.orbit(10.0, -30.0, resolution)
        self._appearance: tuple[str, torch.Tensor] = ("z_da", latent(0, ngp.maps.config.latent_dim)[None])
        self.lights: list[Light] = overhead_rig()
        self.added_lights: list[Light] = []
        self.variant = variant
        self.constants: Constants = ngp.maps.config.constants
        _check_variant(variant, ngp.specular)

    # ------------------------------------------------------------------ handles
    def _changed(self, what: str, old: object = None, new: object = None) -> None:
        """Count a change of ``what`` (not when ``new`` is the value it had: nothing downstream re-runs)."""
        if old is None or not _same(old, new):
            self._versions[what] += 1

    def set_shape(self, z_s: torch.Tensor | None = None, *, seed: int | None = None,
                  mesh: TriangleMesh | str | Path | None = None) -> "NGPScene":
        """The shape: a latent ``z_s`` of G_shape, the latent of ``seed``, or a mesh (a file is loaded
        and normalised; an edited :class:`TriangleMesh` is used as it is)."""
        if sum(x is not None for x in (z_s, seed, mesh)) != 1:
            raise ValueError("set_shape: give exactly one of z_s, seed or mesh")
        if mesh is not None:
            if not isinstance(mesh, TriangleMesh):
                from ngp_mi.geometry.loaders import load_mesh  # only user meshes need the loaders

                mesh = load_mesh(mesh)
            shape = ("mesh", mesh)
        else:
            if self.ngp.shape_model is None:
                raise ValueError("sampling shapes needs a `train shape` run (NGP(..., shape_run=...))")
            shape = ("z_s", as_latent(seed if seed is not None else z_s, self.ngp.shape_model.config.z_dim, "z_s"))
        old, self._shape = self._shape, shape
        self._changed("shape", old, shape)
        return self

    def interpolate_shapes(self, a: torch.Tensor | int, b: torch.Tensor | int, t: float) -> "NGPScene":
        """z_s = slerp(a, b, t) between two latents (or the latents of two seeds)."""
        if self.ngp.shape_model is None:
            raise ValueError("sampling shapes needs a `train shape` run (NGP(..., shape_run=...))")
        dim = self.ngp.shape_model.config.z_dim
        return self.set_shape(slerp(as_latent(a, dim, "z_s"), as_latent(b, dim, "z_s"), t))

    def set_camera(self, camera: Camera | None = None, *, theta: float = 10.0, phi: float = -30.0,
                   distance: float = PAPER_RADIUS, focal_mm: float = PAPER_FOCAL_MM) -> "NGPScene":
        """The camera: ``camera``, or one on the orbit (θ elevation, φ azimuth in degrees, distance to
        the origin, focal length on 36 mm film) at the scene's resolution."""
        if camera is None:
            camera = Camera.orbit(theta, phi, self.resolution, radius=distance, focal_mm=focal_mm)
        check_image_size(camera.height, camera.width, "camera")
        old, self.camera = self.camera, camera
        self._changed("camera", old, camera)
        return self

    def set_appearance(self, z_da: torch.Tensor | None = None, *, seed: int | None = None,
                       exemplar: torch.Tensor | None = None, albedo: torch.Tensor | None = None,
                       exemplar_view: ExemplarView | None = None, fit_steps: int = 30) -> "NGPScene":
        """The appearance: a latent ``z_da``, the latent of ``seed``, μ(E_da(``exemplar``)) of an albedo
        image (1, 3, H, W) in [0, 1], z_da fitted to an ``exemplar_view`` (an albedo map with the
        geometry it was seen on; μ refined by ``fit_steps`` steps, :func:`fit_appearance`), or an
        ``albedo`` map (1, 3, H, W) in [0, 1] used as I_da directly (the paper's direct editing; it
        replaces G_da until another appearance is set)."""
        if sum(x is not None for x in (z_da, seed, exemplar, albedo, exemplar_view)) != 1:
            raise ValueError("set_appearance: give exactly one of z_da, seed, exemplar, exemplar_view or albedo")
        if albedo is not None:
            albedo = torch.as_tensor(albedo, dtype=torch.float32)
            if albedo.shape != (1, 3, self.camera.height, self.camera.width):
                raise ValueError(f"set_appearance: albedo must be (1, 3, {self.camera.height}, {self.camera.width}), "
                                 f"got {tuple(albedo.shape)}")
            appearance = ("albedo", albedo.clamp(0, 1))
        elif exemplar is not None or exemplar_view is not None:
            appearance = ("z_da", self.ngp.appearance(exemplar=exemplar, view=exemplar_view, fit_steps=fit_steps))
        else:
            z = as_latent(seed if seed is not None else z_da, self.ngp.maps.config.latent_dim, "z_da")
            appearance = ("z_da", z[None])
        old, self._appearance = self._appearance, appearance
        self._changed("appearance", old, appearance)
        return self

    def interpolate_appearance(self, a: torch.Tensor | int, b: torch.Tensor | int, t: float) -> "NGPScene":
        """z_da = slerp(a, b, t) between two latents (or the latents of two seeds)."""
        dim = self.ngp.maps.config.latent_dim
        return self.set_appearance(slerp(as_latent(a, dim, "z_da"), as_latent(b, dim, "z_da"), t))

    def set_lights(self, lights: Sequence[Light], added: Sequence[Light] = ()) -> "NGPScene":
        """The lights (directional or point, any number), and the lights NGP-plus adds by R_BP."""
        old = (self.lights, self.added_lights)
        self.lights, self.added_lights = list(lights), list(added)
        self._changed("lights", old, (self.lights, self.added_lights))
        return self

    def set_variant(self, variant: str) -> "NGPScene":
        _check_variant(variant, self.ngp.specular)
        old, self.variant = self.variant, variant
        self._changed("variant", old, variant)
        return self

    def set_constants(self, constants: Constants) -> "NGPScene":
        """k_d, k_s, α of R_BP (and k_d of R_diff)."""
        old, self.constants = self.constants, constants
        self._changed("constants", old, constants)
        return self

    # ------------------------------------------------------------------ stages
    def _stage(self, name: str, key: tuple, compute):
        cached = self._cache.get(name)
        if cached is not None and cached[0] == key:
            return cached[1]
        value = compute()
        self.stage_runs[name] += 1
        self._cache[name] = (key, value)
        return value

    def _extract(self) -> TriangleMesh:
        kind, value = self._shape
        return value if kind == "mesh" else self.ngp.shape(value)

    def _project(self, mesh: TriangleMesh) -> tuple[torch.Tensor, torch.Tensor]:
        projected = project_depth(torch.as_tensor(mesh.vertices, dtype=torch.float32), mesh.faces, self.camera)
        return projected.depth, projected.mask

    @torch.no_grad()
    def render(self, maps: bool = False) -> dict[str, torch.Tensor]:
        """The image (1, 3, H, W, linear radiance); with ``maps``, also depth, mask, normal, albedo,
        the shaded image before the blend and (variants that blend it) the specular map."""
        if self._shape is None:
            raise ValueError("render: set a shape first (set_shape)")
        v, variant = self._versions, self.variant
        k_shape = (v["shape"],)
        mesh = self._stage("extract", k_shape, self._extract)
        k_view = k_shape + (v["camera"],)
        depth, mask = self._stage("project", k_view, lambda: self._project(mesh))
        k_normal = k_view + (variant == "no_gn",)
        normal = self._stage("normals", k_normal,
                             lambda: generate_normals(self.ngp.maps, depth, mask, self.camera, variant))
        kind, appearance = self._appearance
        k_albedo = k_normal + (v["appearance"], variant == "no_gda")
        albedo = self._stage("albedo", k_albedo, lambda: (
            appearance * mask if kind == "albedo" and variant != "no_gda" else
            generate_albedo(self.ngp.maps, depth, mask, self.camera, mesh.bounds, normal, appearance, variant)))
        k_shade = k_albedo + (v["lights"], v["variant"], v["constants"])
        shaded = self._stage("shade", k_shade, lambda: shade_maps(
            normal, albedo, mask, depth, self.camera, self.lights, variant, self.constants, self.added_lights))
        specular = None
        if variant in NEEDS_SPECULAR:
            specular = self._stage("specular", k_albedo, lambda: realistic_specular(
                self.ngp.maps, self.ngp.specular, normal, albedo, mask, self.camera))
        out = {"image": self._stage("blend", k_shade + (specular is not None,),
                                    lambda: add_specular(shaded, specular) if specular is not None else shaded)}
        if maps:
            out.update(depth=depth, mask=mask, normal=normal, albedo=albedo, shaded=shaded)
            if specular is not None:
                out["specular"] = specular
        return out
