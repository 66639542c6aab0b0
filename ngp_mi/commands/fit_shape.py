"""``ngp-mi fit-shape``: recover a shape from images through the differentiable depth projection Π_v
(inverse rendering). The targets are one shape's views of a ``render-dataset`` folder, or the
user's own images with a ``cameras.json`` (:func:`load_user_targets`).

What moves (paper Sec. 3's chain, each stage a function of its own):

* (a) ``start="zs"``: the best of ``zs_candidates`` latents by mask loss, then z_s itself for
  ``zs_steps`` through G_shape, the differentiable iso-surface link and Π_v (:func:`fit_latent`),
  ending on its lowest-loss step (Adam's steps on z_s overshoot and come back: the last is often not it);
  (b) with ``fit_decoder``, the decoder's weights too;
* (d) with ``grid_steps``, after (a)/(b): the fitted field's values on a grid, each node free
  (:func:`fit_grid`), moved by the mask term and the free-space term along the rays of the target's
  background pixels (:mod:`ngp_mi.geometry.carving`) — the one phase that can open a hole;
* (c) the mesh's vertices x — from (a)/(b)/(d), a sphere or a mesh file — through the Laplacian
  parameterisation u = (I + λ L) x (:mod:`ngp_mi.geometry.laplacian`, Nicolet et al. 2021), Adam.

Each step projects the shape into every fitted view with silhouette gradients
(:func:`ngp_mi.render.depth.project_depth`: pixel-averaged coverage c and depth d̄) and minimises
the named terms of :func:`fit_losses`,

    L = w_mask · mean (c − m)² + w_depth · mean m·(d̄ − c·d)² + w_image · mean |I − I_target|,

m, d the target masks and depths. Where the targets carry the pixels' coverage — the alpha of
render-dataset's path-traced images, or a user's soft alpha matte — m in the mask term is that
coverage (``soft_masks``): it is what c estimates, and it places an outline within a pixel, where
a binary mask (is the pixel's centre on the object?) only says on which side of the pixel's centre
it runs; the binary masks still give the IoU. The depth term only looks where the target has the
object (over the target's background it would pull the surface towards the camera; the mask term
shrinks the coverage there instead). The image term (map networks given, targets with images) forms NGP's image
I of each view from d̄ / c and c by G_n, G_da(z_da), R_diff (⊕ G_sp^real) in linear radiance
(:func:`fit_images`), the appearance code z_da fitted beside the shape. A step that loses the shape
from every view or gives a non-finite loss or gradient is undone and retried with half the step size.

Views past ``--held-out`` are scored after the fit (mask IoU, image PSNR / FLIP). Outputs:
``fit.obj`` (or ``.ply``), ``curves.png``, ``sheet.png`` (target against fit, per view),
``progress.gif`` (the fitted silhouette over the steps), ``fit.json`` and ``report.md``; with the
shape's source known (a procedural family or a mesh file), the Chamfer-L2 to it at the start and at
the end. A killed fit resumes from its last state (``state/``: safetensors + a weights-only
optimiser state).
"""

from __future__ import annotations

import copy
import dataclasses
import gc
import json
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from ngp_mi import lock
from ngp_mi.atomic import atomic_path, write_json, write_text
from ngp_mi.camera import Camera
from ngp_mi.data.exr import read_exr
from ngp_mi.data.manifest import load_manifest
from ngp_mi.eval.shape_metrics import chamfer_distance
from ngp_mi.geometry.carving import OccupancyGrid, ray_silhouette_terms
from ngp_mi.geometry.extract import attach_iso_surface_gradient
from ngp_mi.geometry.families import generate
from ngp_mi.geometry.laplacian import LargeSteps
from ngp_mi.geometry.loaders import load_mesh
from ngp_mi.geometry.mesh import TriangleMesh, drop_small_components
from ngp_mi.geometry.occupancy import surface_samples, voxel_iou
from ngp_mi.lights import Light, light_from_dict
from ngp_mi.models.shape import LEVEL
from ngp_mi.render.depth import depth_of_hits, project_depth
from ngp_mi.viz import chw_to_uint8, depth_to_uint8, labelled_grid, linear_to_srgb, save_animation, save_png


MIRROR_AXES = ("x", "y", "z")


@dataclasses.dataclass(frozen=True)
class FitConfig:
    targets: str  # a render-dataset folder
    shape_id: str | None = None  # default: its first shape
    held_out: int = 0  # the last views of the shape, scored but not fitted
    steps: int = 150
    lr: float = 3e-2
    lam: float = 20.0  # λ of I + λ L
    start: str = "sphere"  # "sphere", "zs" (the shape prior's best latent, then z_s fitted) or a mesh file
    zs_candidates: int = 8
    zs_steps: int = 60
    zs_lr: float = 5e-2
    zs_keep_best: bool = True  # end the latent phase on its lowest-loss step, not its last
    fit_decoder: bool = False  # phase (b): the decoder's weights move with z_s
    decoder_lr: float = 1e-4
    extract_resolution: int = 48  # marching-cubes grid of G_shape's surface while z_s is fitted
    grid_steps: int = 0  # phase (d), after (a)/(b): the field's values on a grid, each node free (can open holes)
    grid_resolution: int = 96
    grid_lr: float = 2e-2
    ray_weight: float = 1.0  # phase (d): the grid's free-space term along background rays (opens holes)
    ray_hit_weight: float = 0.0  # and its hit term (max along a target's ray ≥ ℓ): ambiguous where, so off
    rays_per_view: int = 128  # rays of it per view and step, drawn where the mesh and the target mask differ
    ray_samples: int = 64  # occupancy samples per ray
    # after (a)/(b)/(d): pieces of the extracted surface with less than this share of its area are
    # dropped — floaters the grid leaves beside thin parts, which the vertex phase cannot remove. Off:
    # on the two user meshes at 0.003 it changed held-out IoU by +0.003 / −0.002 (bench/RESULTS.md)
    min_component: float = 0.0
    mirror: str = ""  # "x", "y" or "z": the shape is mirror-symmetric about that axis's plane; fitted views mirrored
    sphere_radius: float = 0.4
    sphere_subdivisions: int = 4
    mask_weight: float = 1.0
    soft_masks: bool = True  # the mask term fits the targets' coverage (alpha) where they have it
    depth_weight: float = 1.0
    image_weight: float = 1.0  # with map networks (--model) and path-traced targets; else off
    zda_lr: float = 5e-2  # Adam's step for the appearance code z_da, fitted with the image term
    image_downsample: int = 1  # the image term at 1/k of the targets' resolution (Π_v's maps pooled k × k)
    silhouette: bool = True  # silhouette gradients (else the fast Π_v: interior gradients only)
    spp: int = 8
    boundary_spp: int = 2
    mesh_format: str = "obj"  # of the fitted mesh: obj or ply
    checkpoint_every: int = 25
    frame_every: int = 10
    retries: int = 3  # undone steps in a row (step size halved each time) before a fit gives up

    def __post_init__(self) -> None:
        for name in ("spp", "boundary_spp", "checkpoint_every", "frame_every", "image_downsample", "rays_per_view",
                     "ray_samples"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        if self.steps < (0 if self.start == "zs" else 1):
            raise ValueError(f"--steps must be >= 1 (0 only with --start zs: the latent phase alone), got {self.steps}")
        if self.mirror not in ("", *MIRROR_AXES):
            raise ValueError(f"--mirror must be one of {', '.join(MIRROR_AXES)}, got {self.mirror!r}")
        if self.mesh_format not in ("obj", "ply"):
            raise ValueError(f"--format must be obj or ply, got {self.mesh_format!r}")
        if self.fit_decoder and self.start != "zs":
            raise ValueError("--fit-decoder needs --start zs (the decoder is the shape prior's)")
        if not (self.lr > 0 and self.zda_lr > 0 and self.decoder_lr > 0 and self.lam >= 0 and self.mask_weight >= 0 and self.depth_weight >= 0
                and self.image_weight >= 0 and self.ray_weight >= 0 and self.ray_hit_weight >= 0):
            raise ValueError("--lr must be > 0 and --lam, --mask-weight, --depth-weight, --image-weight, --ray-weight >= 0")
        if self.grid_steps and self.start != "zs":
            raise ValueError("--grid-steps needs --start zs (phase (d) starts from the shape prior's field)")
        if self.grid_steps < 0 or self.grid_resolution < 8 or not self.grid_lr > 0:
            raise ValueError(f"--grid-steps must be >= 0, --grid-resolution >= 8 and --grid-lr > 0, got "
                             f"{self.grid_steps}, {self.grid_resolution}, {self.grid_lr}")
        if not 0 <= self.min_component < 1:
            raise ValueError(f"--min-component must lie in [0, 1), got {self.min_component}")
        if self.mask_weight == 0 and self.depth_weight == 0:
            raise ValueError("fit-shape needs a loss: --mask-weight or --depth-weight > 0")


@dataclasses.dataclass
class Targets:
    cameras: list[Camera]
    mask: torch.Tensor  # (N, 1, H, W)
    depth: torch.Tensor | None  # (N, 1, H, W), 0 off the mask; None: no depth targets (the user's images)
    record: dict[str, Any]  # the first view's manifest record
    images: torch.Tensor | None = None  # (N, 3, H, W) path-traced, linear radiance (render-dataset --real-spp)
    lights: list[list[Light]] | None = None  # each image's lights
    coverage: torch.Tensor | None = None  # (N, 1, H, W) each pixel's covered fraction (alpha), where known

    @property
    def fit_mask(self) -> torch.Tensor:
        """What the mask term fits: the coverage where the targets have it, else the binary masks."""
        return self.mask if self.coverage is None else self.coverage


CAMERAS_FILE = "cameras.json"


def load_user_targets(root: str | Path) -> Targets:
    """A user's own views: ``ROOT/cameras.json`` lists ``{"views": [{"image": FILE, "K": 3×3, "E":
    3×4 or 4×4 (OpenCV, world → camera), "mask": FILE (optional: else the image's alpha channel),
    "lights": [...] (optional: else the overhead rig)}]}``. Images (PNG / JPEG in sRGB, or EXR in
    linear radiance) share one size; there are no depth targets. Errors name the file, view and field."""
    from PIL import Image

    from ngp_mi.data.datasets import read_image
    from ngp_mi.lights import overhead_rig

    root = Path(root)
    path = root / CAMERAS_FILE
    try:
        views = json.loads(path.read_text())["views"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: cannot read the views ({type(exc).__name__}: {exc}); expected "
                         '{"views": [{"image": ..., "K": ..., "E": ...}, ...]}') from None
    if not isinstance(views, list) or not views:
        raise ValueError(f"{path}: 'views' must be a non-empty list")
    cameras, masks, alphas, images, lights = [], [], [], [], []
    for k, view in enumerate(views):
        where = f"{path}: view {k}"
        if not isinstance(view, dict) or "image" not in view:
            raise ValueError(f"{where}: needs an 'image' file")
        where = f"{path}: view {k} ({view['image']})"
        for field in ("K", "E"):
            if field not in view:
                raise ValueError(f"{where}: no camera field {field!r}")
        image_path = root / view["image"]
        image = read_image(image_path, linear=True)
        height, width = image.shape[:2]
        if images and image.shape != images[0].shape:
            raise ValueError(f"{where}: {width}x{height}, the first view is {images[0].shape[1]}x{images[0].shape[0]}")
        E = np.asarray(view["E"], dtype=np.float64)
        try:
            camera = Camera.from_K_E(np.asarray(view["K"], dtype=np.float64), E[:3] if E.shape == (4, 4) else E,
                                     width, height)
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{where}: inconsistent camera ({exc})") from None
        if not (0 <= camera.cx <= width and 0 <= camera.cy <= height):
            raise ValueError(f"{where}: the principal point ({camera.cx}, {camera.cy}) lies outside the "
                             f"{width}x{height} image")
        if "mask" in view:
            mask = np.asarray(Image.open(root / view["mask"]).convert("L"), np.float32) / 255.0
        else:
            with Image.open(image_path) as im:
                if "A" not in im.getbands():
                    raise ValueError(f"{where}: no mask — give a 'mask' file or an image with an alpha channel")
                mask = np.asarray(im.getchannel("A"), np.float32) / 255.0
        if mask.shape != (height, width):
            raise ValueError(f"{where}: the mask is {mask.shape[1]}x{mask.shape[0]}, the image {width}x{height}")
        cameras.append(camera)
        alphas.append(mask)
        masks.append((mask > 0.5).astype(np.float32))
        images.append(image * masks[-1][..., None])
        lights.append([light_from_dict(light, f"{where}, light {j}") for j, light in enumerate(view["lights"])]
                      if "lights" in view else overhead_rig())
    mask_tensor = torch.from_numpy(np.stack(masks)[:, None])
    soft = any(((a > 0) & (a < 1)).any() for a in alphas)  # a matte, not a binary mask
    return Targets(cameras, mask_tensor, None, {"shape_id": root.name, "source": "user"},
                   torch.from_numpy(np.stack(images).transpose(0, 3, 1, 2).copy()), lights,
                   torch.from_numpy(np.stack(alphas)[:, None].copy()) if soft else None)


def load_targets(root: str | Path, shape_id: str | None = None) -> Targets:
    """The views of one shape of a render-dataset folder, or a folder of the user's own views with a
    ``cameras.json`` (:func:`load_user_targets`); errors name the folder, shape or file."""
    if (Path(root) / CAMERAS_FILE).exists():
        return load_user_targets(root)
    records = load_manifest(root)
    shape_id = shape_id or records[0]["shape_id"]
    mine = [r for r in records if r["shape_id"] == shape_id]
    if not mine:
        shapes = sorted({r["shape_id"] for r in records})
        raise ValueError(f"{root}: no views of shape {shape_id!r} (it has {', '.join(shapes[:5])}…)")
    cameras, masks, depths, images, lights, alphas = [], [], [], [], [], []
    with_images = all("real" in r["files"] and isinstance(r.get("lights"), list) for r in mine)
    for r in mine:
        channels = set(r["channels"])
        if not {"mask", "depth"} <= channels:
            raise ValueError(f"{root}/{r['files']['maps']}: needs mask and depth channels, has {sorted(channels)}")
        try:
            cameras.append(Camera.from_K_E(np.asarray(r["K"]), np.asarray(r["E"]), r["width"], r["height"]))
        except (KeyError, ValueError) as exc:
            raise ValueError(f"{root}: view {r['view']} of {shape_id}: no usable camera ({exc})") from None
        maps = read_exr(Path(root) / r["files"]["maps"], ["mask", "depth"])
        for name, values in maps.items():
            if not np.isfinite(values).all():
                raise ValueError(f"{root}/{r['files']['maps']}: channel {name!r} has non-finite values")
        masks.append(maps["mask"])
        depths.append(maps["depth"] * maps["mask"])
        if with_images:
            real = read_exr(Path(root) / r["files"]["real"])
            if "rgb" not in real:
                raise ValueError(f"{root}/{r['files']['real']}: no 'rgb' layer, has {sorted(real)}")
            if not all(np.isfinite(values).all() for values in real.values()):
                raise ValueError(f"{root}/{r['files']['real']}: the image has non-finite values")
            images.append(real["rgb"].transpose(2, 0, 1))
            alphas.append(real.get("alpha"))  # datasets rendered before alpha was written have none
            lights.append([light_from_dict(light, f"{root}: view {r['view']} of {shape_id}, light {k}")
                           for k, light in enumerate(r["lights"])])
    stack = lambda xs: torch.from_numpy(np.stack(xs)[:, None].astype(np.float32))  # noqa: E731
    return Targets(cameras, stack(masks), stack(depths), mine[0],
                   torch.from_numpy(np.stack(images).astype(np.float32)) if with_images else None,
                   lights if with_images else None,
                   stack(alphas) if with_images and all(a is not None for a in alphas) else None)


def mirror_views(targets: Targets, fitted: int, axis: str) -> Targets:
    """The targets with each of the first ``fitted`` views' mirror image added after them (held-out
    views stay last), for a shape symmetric about the plane through the origin normal to ``axis``
    (M = diag(±1) flipping that axis; procedural chairs and cars about x).

    For a symmetric shape S = M S, a camera (R, t) sees at pixel u what the camera
    (F R M, F t) with principal point W − c_x sees at W − u (F = diag(−1, 1, 1) flips the image's
    x axis, so F R M is again a rotation): the mirrored view is the target flipped left–right,
    under the mirrored lights, with the same depths. Eight views of a chair become sixteen
    without rendering anything."""
    flip = np.diag([-1.0, 1.0, 1.0])
    mirror = np.diag(np.where(np.arange(3) == MIRROR_AXES.index(axis), -1.0, 1.0))
    cameras = [dataclasses.replace(c, R=flip @ c.R @ mirror, t=flip @ c.t, cx=c.width - c.cx, theta_deg=None,
                                   phi_deg=None) for c in targets.cameras[:fitted]]

    def both(views: torch.Tensor | None) -> torch.Tensor | None:
        return None if views is None else torch.cat([views[:fitted], views[:fitted].flip(-1), views[fitted:]])

    lights = None
    if targets.lights is not None:
        def mirrored(light: Light) -> Light:
            field = "direction" if hasattr(light, "direction") else "position"
            return dataclasses.replace(light, **{field: tuple(float(v) for v in mirror @ np.asarray(getattr(light, field)))})
        lights = targets.lights[:fitted] + [[mirrored(x) for x in ls] for ls in targets.lights[:fitted]] \
            + targets.lights[fitted:]
    return Targets(targets.cameras[:fitted] + cameras + targets.cameras[fitted:], both(targets.mask),
                   both(targets.depth), targets.record, both(targets.images), lights, both(targets.coverage))


def fit_losses(coverage: torch.Tensor, depth: torch.Tensor, target_mask: torch.Tensor,
               target_depth: torch.Tensor | None,
               mask_weight: float, depth_weight: float, image: torch.Tensor | None = None,
               target_image: torch.Tensor | None = None, image_weight: float = 0.0) -> dict[str, torch.Tensor]:
    """The fit's named loss terms (module docstring) and their weighted sum ``total``; with ``image``,
    also the image term mean |I − I_target| in linear radiance."""
    terms = {"mask": (coverage - target_mask).square().mean(),
             "depth": (target_mask * (depth - coverage * target_depth)).square().mean() if target_depth is not None
             else depth.new_zeros(())}  # no depth targets (the user's own images)
    terms["total"] = mask_weight * terms["mask"] + depth_weight * terms["depth"]
    if image is not None:
        terms["image"] = (image - target_image).abs().mean()
        terms["total"] = terms["total"] + image_weight * terms["image"]
    return terms


@dataclasses.dataclass
class ImageTerm:
    """What the image term needs: NGP's networks (:class:`ngp_mi.pipeline.NGP`), the variant that
    forms the image, and the appearance code z_da (1, D) fitted beside the shape."""
    ngp: Any
    variant: str
    z_da: torch.Tensor


def fit_images(term: ImageTerm, depth: torch.Tensor, coverage: torch.Tensor, cameras: list[Camera],
               bounds: np.ndarray, lights: list[list[Light]], downsample: int = 1) -> torch.Tensor:
    """NGP's image (N, 3, H / k, W / k) of each view from Π_v's pixel-averaged depth d̄ and coverage c,
    with gradients into both and into z_da: the networks read the depth d̄ / c of the covered samples
    and take c as the mask (:func:`ngp_mi.pipeline.ngp_image`, which weights the image by it), so
    the silhouette gradients reach the image too.

    ``downsample`` k > 1 forms the image at 1/k of the resolution from d̄ and c average-pooled k × k —
    exactly Π_v's pixel averages at the lower resolution with k² times the samples — for networks
    trained at that resolution, at 1/k² of their cost."""
    from ngp_mi.pipeline import ngp_image  # the image formation of the paper, one stage per function

    if downsample > 1:
        depth, coverage = pool_views(depth, downsample), pool_views(coverage, downsample)
        cameras = [c.with_resolution(c.width // downsample, c.height // downsample) for c in cameras]
    hits, maps = depth_of_hits(depth, coverage), term.ngp.maps
    return torch.cat([ngp_image(maps, term.ngp.specular, hits[i:i + 1], coverage[i:i + 1], camera, bounds,
                                term.z_da, lights[i], term.variant)["image"] for i, camera in enumerate(cameras)])


def pool_views(views: torch.Tensor, k: int) -> torch.Tensor:
    """(N, C, H, W) averaged over k × k pixel blocks: a pixel average of pixel averages (a box filter,
    right for coverage, d̄ and linear radiance alike)."""
    return views if k == 1 else torch.nn.functional.avg_pool2d(views, k)


def source_mesh(record: dict[str, Any]) -> TriangleMesh | None:
    """The target's true shape when the dataset names it (a procedural family or a mesh file), else None."""
    if record.get("source") == "procedural":
        return generate(record["origin"], int(record["shape_id"].rsplit("/", 1)[1])).mesh()
    if record.get("source") == "mesh" and Path(record["origin"]).exists():
        return load_mesh(record["origin"])
    return None


def _chamfer(a: TriangleMesh, b: TriangleMesh, count: int = 4096) -> float:
    rng = np.random.default_rng(0)
    pa, pb = (torch.from_numpy(surface_samples(m, count, rng)).double() for m in (a, b))
    return float(chamfer_distance(pa, pb))


def _iou(coverage: torch.Tensor, mask: torch.Tensor) -> float:
    """Mask IoU of a (soft) coverage against a target mask, both thresholded at 1/2."""
    return voxel_iou((coverage > 0.5).numpy(), (mask > 0.5).numpy())


def _step_losses(vertices: torch.Tensor, faces: np.ndarray, targets: Targets, fitted: slice, config: FitConfig,
                 step: int, image_term: ImageTerm | None = None) -> tuple[Any, dict[str, torch.Tensor]]:
    """One step's projection of the fitted views (silhouette samples seeded by the step) and its loss terms."""
    maps = project_depth(vertices, faces, targets.cameras[fitted], silhouette_grad=config.silhouette, spp=config.spp,
                         boundary_spp=config.boundary_spp, seed=step)
    image = target_image = None
    if image_term is not None:
        corners = vertices.detach().numpy()
        image = fit_images(image_term, maps.depth, maps.mask, targets.cameras[fitted],
                           np.stack([corners.min(0), corners.max(0)]), targets.lights[fitted], config.image_downsample)
        target_image = pool_views(targets.images[fitted], config.image_downsample)
    target_depth = targets.depth[fitted] if targets.depth is not None else None
    return maps, fit_losses(maps.mask, maps.depth, targets.fit_mask[fitted], target_depth, config.mask_weight,
                            config.depth_weight, image, target_image, config.image_weight)


def _descend(moving: list[torch.Tensor], optimizer: torch.optim.Optimizer, steps: int,
             step_terms: Callable[[int], dict[str, torch.Tensor] | None], log: Callable[[str], None], phase: str
             ) -> tuple[list[dict[str, float]], int, list[torch.Tensor], int, list[torch.Tensor]]:
    """The steps of a phase that moves a field (z_s and the decoder, or a grid): ``step_terms(step)``
    gives the named loss terms, or None when the parameters give no shape — then the last step is
    undone and the step size halved (logged); a non-finite gradient skips the step (logged).

    Returns the history, the number of halvings, the lowest-loss parameters seen and their step
    (1-based; noisy steps end anywhere, so a phase may end there rather than on its last step), and
    the parameters of the last step that gave a shape."""
    previous = [p.detach().clone() for p in moving]
    history, halvings = [], 0
    best_total, best, best_step = float("inf"), previous, 0
    for step in range(steps):
        terms = step_terms(step)
        if terms is None:
            for p, kept in zip(moving, previous):
                p.data.copy_(kept)
            for group in optimizer.param_groups:
                group["lr"] *= 0.5
            halvings += 1
            log(f"fit-shape: {phase} step {step} gave an empty shape; undone, step size halved")
            continue
        optimizer.zero_grad(set_to_none=True)
        terms["total"].backward()
        previous = [p.detach().clone() for p in moving]
        total = float(terms["total"].detach())
        if total < best_total:
            best_total, best, best_step = total, previous, step + 1
        if all(p.grad is None or torch.isfinite(p.grad).all() for p in moving):
            optimizer.step()
        else:
            log(f"fit-shape: {phase} step {step}: a non-finite gradient; skipped")
        history.append({"step": step + 1, **{k: float(v.detach()) for k, v in terms.items()}})
    return history, halvings, best, best_step, previous


def fit_latent(shape_model: Any, targets: Targets, fitted: slice, config: FitConfig,
               log: Callable[[str], None], image_term: ImageTerm | None = None
               ) -> tuple[TriangleMesh, Callable[[torch.Tensor], torch.Tensor], dict[str, Any]]:
    """Phase (a): the best of ``zs_candidates`` latents by mask loss, then z_s fitted through G_shape
    (with ``fit_decoder``, the decoder's weights too, at ``decoder_lr``: phase (b)); with an image
    term, z_da moves beside them.

    A step whose latent gives an empty shape is undone and the step size halved (logged), so a fit
    never stops on a shape with nothing to project. Phase (b) moves a copy of the decoder: the
    caller's prior stays as trained (one prior serves many fits). Returns the mesh, the fitted
    occupancy field (points → occupancy) and the phase's record.
    """
    from ngp_mi.pipeline import latent  # the one rule of seeded latents

    if config.fit_decoder:
        shape_model = copy.deepcopy(shape_model)
        trained = [p.detach().clone() for p in shape_model.decoder.parameters()]
    for p in shape_model.parameters():
        p.requires_grad_(False)  # only z_s moves (and the decoder in phase (b))
    decoder = list(shape_model.decoder.parameters()) if config.fit_decoder else []
    for p in decoder:
        p.requires_grad_(True)
    dim, cams = shape_model.config.z_dim, targets.cameras[fitted]
    scores, candidates = [], {}
    for seed in range(config.zs_candidates):
        mesh = shape_model.shape(latent(seed, dim), resolution=config.extract_resolution).mesh
        if mesh is None:
            continue
        with torch.no_grad():
            maps = project_depth(torch.as_tensor(mesh.vertices, dtype=torch.float32), mesh.faces, cams)
        scores.append((float((maps.mask - targets.mask[fitted]).square().mean()), seed))
        candidates[seed] = mesh
    if not scores:
        raise ValueError(f"fit-shape: none of {config.zs_candidates} latents of the shape prior gives a shape")
    best_loss, best_seed = min(scores)
    log(f"fit-shape: start z_s of seed {best_seed} (mask loss {best_loss:.4f}, best of {len(scores)})")
    truth = source_mesh(targets.record)
    chamfer_zs_start = _chamfer(candidates[best_seed], truth) if truth is not None else None
    z = latent(best_seed, dim).clone().requires_grad_(True)
    moving = [z, *decoder, *([image_term.z_da] if image_term is not None else [])]
    groups = [{"params": [z], "lr": config.zs_lr}]
    if decoder:
        groups.append({"params": decoder, "lr": config.decoder_lr})
    if image_term is not None:
        groups.append({"params": [image_term.z_da], "lr": config.zda_lr})

    def step_terms(step: int) -> dict[str, torch.Tensor] | None:
        surface = shape_model.differentiable_surface(z, resolution=config.extract_resolution)
        return None if surface is None else _step_losses(*surface, targets, fitted, config, step, image_term)[1]

    history, halvings, best, best_step, previous = _descend(moving, torch.optim.Adam(groups), config.zs_steps,
                                                            step_terms, log, "z_s")
    if config.zs_keep_best:
        for p, kept in zip(moving, best):
            p.data.copy_(kept)
    extraction = shape_model.shape(z.detach(), resolution=config.extract_resolution)
    if extraction.mesh is None:
        for p, kept in zip(moving, previous):
            p.data.copy_(kept)
        extraction = shape_model.shape(z.detach(), resolution=config.extract_resolution)
    for p in decoder:
        p.requires_grad_(False)
    end_step = best_step if config.zs_keep_best else (history[-1]["step"] if history else 0)
    if history:
        end = next(h for h in history if h["step"] == end_step)
        log(f"fit-shape: z_s fitted, mask loss {history[0]['mask']:.4f} → {end['mask']:.4f} (step {end_step})")
    else:
        log("fit-shape: no z_s step")
    with torch.no_grad():
        field = shape_model.field(shape_model.code_of(z.detach())[0])  # G_shape as fitted, for phase (d)
    return extraction.mesh, field, {"zs_seed": best_seed, "zs_history": history, "zs_halvings": halvings,
                             "chamfer_zs_start": chamfer_zs_start,  # the best latent's shape, before z_s moved
                             "zs_end_step": end_step,
                             "decoder_fitted": bool(decoder),
                             **({"decoder_moved_by": max(float((p - t).abs().max()) for p, t in zip(decoder, trained))}
                                if decoder else {}),
                             **({"z_da": image_term.z_da.detach()[0].tolist()} if image_term is not None else {})}


def fit_grid(field: Callable[[torch.Tensor], torch.Tensor], targets: Targets, fitted: slice, config: FitConfig,
             log: Callable[[str], None], image_term: ImageTerm | None = None) -> tuple[TriangleMesh, dict[str, Any]]:
    """Phase (d): the occupancy field of (a)/(b) sampled on a ``grid_resolution``³ grid whose node
    values then move freely (:class:`~ngp_mi.geometry.carving.OccupancyGrid`), for ``grid_steps``
    steps of the mask term (through the iso-surface link) and the ray terms.

    A decoder answers a loss on one part by moving the whole shape; a grid node moves only the
    surface around it, so the free-space term can open a gap (between a chair back's slats) without
    eroding the rest, a change of topology the vertex phase cannot make. Ends on the lowest-loss step;
    a step that empties the grid is undone with half the step size (:func:`_descend`).
    """
    grid = OccupancyGrid.from_field(field, config.grid_resolution, LEVEL)
    moving = [grid.values, *([image_term.z_da] if image_term is not None else [])]
    optimizer = torch.optim.Adam([{"params": [grid.values], "lr": config.grid_lr}]
                                 + ([{"params": [image_term.z_da], "lr": config.zda_lr}] if image_term is not None else []))

    def step_terms(step: int) -> dict[str, torch.Tensor] | None:
        mesh = grid.mesh(LEVEL)
        if mesh is None:
            return None
        vertices = attach_iso_surface_gradient(torch.as_tensor(mesh.vertices, dtype=torch.float32), grid)
        maps, terms = _step_losses(vertices, mesh.faces, targets, fitted, config, step, image_term)
        rays = ray_silhouette_terms(grid, targets.cameras[fitted], maps.mask, targets.mask[fitted],
                                    config.rays_per_view, config.ray_samples, level=LEVEL, seed=step)
        return {**terms, **rays, "total": terms["total"] + config.ray_weight * rays["free"]
                + config.ray_hit_weight * rays["hit"]}

    history, _, best, best_step, _ = _descend(moving, optimizer, config.grid_steps, step_terms, log, "grid")
    for p, kept in zip(moving, best):
        p.data.copy_(kept)
    mesh = grid.mesh(LEVEL)
    if history:
        end = next(h for h in history if h["step"] == best_step)
        log(f"fit-shape: grid fitted, mask loss {history[0]['mask']:.4f} → {end['mask']:.4f} (step {best_step})")
    return mesh, {"grid_history": history, "grid_end_step": best_step,
                  **({"z_da": image_term.z_da.detach()[0].tolist()} if image_term is not None else {})}


def _start_mesh(config: FitConfig) -> TriangleMesh:
    if config.start == "sphere":
        import trimesh

        sphere = trimesh.creation.icosphere(config.sphere_subdivisions, radius=config.sphere_radius)
        return TriangleMesh(np.asarray(sphere.vertices, np.float32), np.asarray(sphere.faces), name="sphere")
    return load_mesh(config.start)


def _image_term(config: FitConfig, targets: Targets, ngp: Any, log: Callable[[str], None]) -> ImageTerm | None:
    """The image term when it can be formed (map networks given, targets with path-traced images)."""
    if config.image_weight == 0:
        return None
    if ngp is None or targets.images is None:
        log("fit-shape: no image term (" + ("no map networks: --model or --maps-run" if ngp is None else
                                           "the targets have no path-traced images: render-dataset --real-spp") + ")")
        return None
    variant = "ngp" if ngp.specular is not None else "no_sp"
    for module in (ngp.maps, ngp.specular):
        if module is not None:
            module.eval().requires_grad_(False)  # the networks stay as trained; only the scene moves
    return ImageTerm(ngp, variant, torch.zeros(1, ngp.maps.config.latent_dim, requires_grad=True))


def fit_shape(config: FitConfig, out: str | Path, shape_model: Any = None, ngp: Any = None,
              log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run (or resume) the fit; returns the summary written to ``fit.json``. ``shape_model``: the shape
    prior (:class:`ngp_mi.models.shape.ShapeModel`) for ``start="zs"``; ``ngp``: the map networks
    (:class:`ngp_mi.pipeline.NGP`) for the image term, z_da fitted with it. One fit at a time writes
    into ``out``: a second one is refused, naming the first (:mod:`ngp_mi.lock`)."""
    out = Path(out)
    with lock.exclusive(out / "fit-shape.lock", f"the fit in {out}"):
        summary = _fit_shape(config, out, shape_model, ngp, log)
    # matplotlib's tight_layout can leave a reference cycle through our frames (an exception it catches
    # during an import), which keeps the vertices' Cholesky factor alive; freed only at interpreter
    # exit, after cholespy's module, nanobind reports it there as a leak (`make demo` printed it)
    gc.collect()
    return summary


def _fit_shape(config: FitConfig, out: Path, shape_model: Any, ngp: Any, log: Callable[[str], None]) -> dict[str, Any]:
    targets = load_targets(config.targets, config.shape_id)
    image_term = _image_term(config, targets, ngp, log)
    if not config.soft_masks:
        targets = dataclasses.replace(targets, coverage=None)
    log("fit-shape: the mask term fits " + ("the images' alpha (each pixel's coverage)" if targets.coverage is not None
                                            else "the binary masks"))
    if targets.depth is None and config.depth_weight:
        log("fit-shape: the targets have no depths (the user's own images): the depth term is off")
    n = len(targets.cameras)
    k = config.image_downsample
    if image_term is not None and any(c.width % k or c.height % k for c in targets.cameras):
        raise ValueError(f"--image-downsample {k} does not divide the targets' resolution "
                         f"{targets.cameras[0].width}×{targets.cameras[0].height} ({config.targets})")
    if not 0 <= config.held_out < n:
        raise ValueError(f"--held-out {config.held_out}: the shape has {n} views; keep at least one to fit")
    if config.mirror:
        targets = mirror_views(targets, n - config.held_out, config.mirror)
        log(f"fit-shape: {n - config.held_out} fitted views and their mirror images about {config.mirror} = 0")
        n = len(targets.cameras)
    fitted = slice(0, n - config.held_out)
    latent_phase: dict[str, Any] = {}
    if config.start == "zs":
        if shape_model is None:
            raise ValueError("fit-shape --start zs needs a shape prior: --model or --shape-run")
        start_file = out / "state" / "start.safetensors"
        if (out / "state" / "latent.json").exists():  # phase (a) is done: its mesh was kept
            kept = load_file(start_file)
            start = TriangleMesh(kept["vertices"].numpy(), kept["faces"].numpy(), name="G_shape(z_s)")
            latent_phase = json.loads((out / "state" / "latent.json").read_text())
            if image_term is not None and "z_da" in latent_phase:  # the vertices start from phase (a)'s appearance
                image_term.z_da.data.copy_(torch.tensor(latent_phase["z_da"])[None])
        else:
            start, field, latent_phase = fit_latent(shape_model, targets, fitted, config, log, image_term)
            if config.grid_steps:
                start, grid_phase = fit_grid(field, targets, fitted, config, log, image_term)
                latent_phase.update(grid_phase)
            if config.min_component:
                start, dropped = drop_small_components(start, config.min_component)
                latent_phase["components_dropped"] = dropped
                if dropped:
                    log(f"fit-shape: {dropped} piece(s) under {100 * config.min_component:g} % of the surface dropped")
            with atomic_path(start_file) as tmp:
                save_file({"vertices": torch.as_tensor(start.vertices, dtype=torch.float32).contiguous(),
                           "faces": torch.as_tensor(np.asarray(start.faces, np.int64)).contiguous()}, tmp)
            write_json(out / "state" / "latent.json", latent_phase)  # last: it commits phase (a)
    else:
        start = _start_mesh(config)
    faces = start.faces
    param = LargeSteps(faces, len(start.vertices), config.lam)
    u = param.to_u(torch.as_tensor(start.vertices)).requires_grad_(True)
    groups = [{"params": [u], "lr": config.lr}]
    if image_term is not None:
        groups.append({"params": [image_term.z_da], "lr": config.zda_lr})
    optimizer = torch.optim.Adam(groups)
    history: list[dict[str, float]] = []
    frames: list[np.ndarray] = []
    state_dir, step = out / "state", 0
    settings = dataclasses.asdict(config)
    if (state_dir / "state.json").exists():
        saved = json.loads((state_dir / "state.json").read_text())
        if saved["config"] != json.loads(json.dumps(settings)):
            raise ValueError(f"{state_dir}: this fit was started with other settings; use a new --out")
        saved_tensors = load_file(state_dir / "u.safetensors")
        u.data.copy_(saved_tensors["u"])
        if image_term is not None:
            image_term.z_da.data.copy_(saved_tensors["z_da"])
        optimizer.load_state_dict(torch.load(state_dir / "optimizer.pt", weights_only=True))
        step, history = saved["step"], saved["history"]
        log(f"fit-shape: resumed at step {step} from {state_dir}")
    began, first = time.perf_counter(), step
    if step == 0:
        with torch.no_grad():
            seen = project_depth(param.vertices(u).detach(), faces, targets.cameras[fitted]).mask
        if not seen.any():
            raise ValueError(f"fit-shape: no fitted view of {config.targets} sees the start shape ({config.start}); "
                             "start from a shape inside the cameras' views")
    previous, troubles = u.detach().clone(), 0
    while step < config.steps:
        maps, terms = _step_losses(param.vertices(u), faces, targets, fitted, config, step, image_term)
        problem = _step_problem(maps.mask, terms["total"])
        if problem is None:
            optimizer.zero_grad(set_to_none=True)
            terms["total"].backward()
            if not all(torch.isfinite(p.grad).all() for group in groups for p in group["params"]):
                problem = "a non-finite gradient"
        if problem is not None:  # undo the step that led here and retry with half of it
            troubles += 1
            if troubles > config.retries:
                raise RuntimeError(f"fit-shape: {problem} at step {step}, {troubles} times in a row after halving the "
                                   f"step size; the state saved in {state_dir} holds none of it")
            u.data.copy_(previous)
            optimizer.state.clear()  # Adam's moments point the way that failed
            for group in optimizer.param_groups:
                group["lr"] *= 0.5
            log(f"fit-shape: step {step}: {problem}; the last step undone, step size halved")
            continue
        troubles = 0
        previous = u.detach().clone()
        optimizer.step()
        step += 1
        history.append({"step": step, **{k: float(v.detach()) for k, v in terms.items()}})
        if step % config.frame_every == 0 or step == 1:
            frames.append(_overlay(maps.mask[0, 0].detach(), targets.mask[0, 0]))
        rate = (step - first) / (time.perf_counter() - began)
        if step % 10 == 0 or step == config.steps:
            log(f"fit-shape: step {step}/{config.steps}  loss {history[-1]['total']:.5f}  {rate:.2f} steps/s  "
                f"ETA {(config.steps - step) / rate:.0f} s")
        if step % config.checkpoint_every == 0 or step == config.steps:
            _save_state(state_dir, u, optimizer, step, history, settings, image_term)
    return _finish(config, out, targets, param, u, faces, start, history, frames, log, latent_phase, image_term)


def _step_problem(coverage: torch.Tensor, total: torch.Tensor) -> str | None:
    """Why a step cannot be taken: the shape left every fitted view (no gradient would bring it
    back), or a non-finite loss."""
    if not bool(coverage.detach().gt(0).any()):
        return "the shape left every fitted view"
    if not bool(torch.isfinite(total.detach())):
        return "a non-finite loss"
    return None


def _overlay(fit: torch.Tensor, target: torch.Tensor) -> np.ndarray:
    """Target in blue, fit in orange, both white."""
    t, f = target.numpy() > 0.5, fit.numpy() > 0.5
    image = np.zeros((*t.shape, 3), np.uint8)
    image[t] = (60, 110, 230)
    image[f] = (240, 150, 40)
    image[t & f] = (235, 235, 235)
    return image


def _save_state(folder: Path, u: torch.Tensor, optimizer: torch.optim.Optimizer, step: int,
                history: list[dict[str, float]], settings: dict[str, Any], image_term: ImageTerm | None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    tensors = {"u": u.detach().contiguous()}
    if image_term is not None:
        tensors["z_da"] = image_term.z_da.detach().contiguous()
    for name, tensor in tensors.items():
        if not torch.isfinite(tensor).all():  # the loop never takes such a step; refuse rather than write it
            raise RuntimeError(f"fit-shape: refusing to save a non-finite {name} at step {step} in {folder}")
    with atomic_path(folder / "u.safetensors") as tmp:
        save_file(tensors, tmp)
    with atomic_path(folder / "optimizer.pt") as tmp:
        torch.save(optimizer.state_dict(), tmp)
    write_json(folder / "state.json", {"step": step, "history": history, "config": settings})  # last: it commits


def _finish(config: FitConfig, out: Path, targets: Targets, param: LargeSteps, u: torch.Tensor, faces: np.ndarray,
            start: TriangleMesh, history: list[dict[str, float]], frames: list[np.ndarray],
            log: Callable[[str], None], latent_phase: dict[str, Any], image_term: ImageTerm | None) -> dict[str, Any]:
    with torch.no_grad():
        vertices = param.vertices(u).detach()
        maps = project_depth(vertices, faces, targets.cameras)
        start_vertices = torch.as_tensor(start.vertices, dtype=torch.float32)
        start_maps = project_depth(start_vertices, faces, targets.cameras)
        before = start_maps.mask
    mesh = TriangleMesh(vertices.numpy(), faces, name="fit")
    _write_mesh(out / f"fit.{config.mesh_format}", mesh)
    n, fitted = len(targets.cameras), len(targets.cameras) - config.held_out
    ious = [_iou(maps.mask[i, 0], targets.mask[i, 0]) for i in range(n)]
    truth = source_mesh(targets.record)
    summary = {"config": dataclasses.asdict(config), "shape_id": targets.record["shape_id"], "views": n,
               "fitted_views": fitted, "steps": len(history) and history[-1]["step"],
               "mask_target": "binary" if targets.coverage is None else "coverage",
               "loss_start": history[0]["total"] if history else None,
               "loss_end": history[-1]["total"] if history else None,
               "mask_iou_start": float(np.mean([_iou(before[i, 0], targets.mask[i, 0]) for i in range(fitted)])),
               "mask_iou_fitted": float(np.mean(ious[:fitted])),
               "mask_iou_held_out": float(np.mean(ious[fitted:])) if config.held_out else None,
               "chamfer_start": _chamfer(start, truth) if truth is not None else None,
               "chamfer_end": _chamfer(mesh, truth) if truth is not None else None,
               "mask_iou_held_out_start": (float(np.mean([_iou(before[i, 0], targets.mask[i, 0]) for i in range(fitted, n)]))
                                           if config.held_out else None),
               "start": config.start, **{k: v for k, v in latent_phase.items() if not k.endswith("_history")}}
    phases = [("z_s", latent_phase.get("zs_history", [])), ("grid", latent_phase.get("grid_history", [])),
              ("vertices", history)]  # one curve through the phases, in their order
    _plot(phases, out / "curves.png")
    target_depth = targets.depth if targets.depth is not None else torch.zeros_like(targets.mask)
    rows = [[_overlay(maps.mask[i, 0], targets.mask[i, 0]), depth_to_uint8(target_depth[i, 0], targets.mask[i, 0]),
             depth_to_uint8(maps.depth[i, 0], maps.mask[i, 0])] for i in range(n)]
    columns = ["mask: target / fit / both", "target depth", "fitted depth"]
    if image_term is not None:
        with torch.no_grad():
            z_fit = image_term.z_da.detach()
            k = config.image_downsample  # scored where it was fitted
            images = {"start": fit_images(dataclasses.replace(image_term, z_da=torch.zeros_like(z_fit)),
                                          start_maps.depth, start_maps.mask, targets.cameras, start.bounds,
                                          targets.lights, k),
                      "end": fit_images(dataclasses.replace(image_term, z_da=z_fit), maps.depth, maps.mask,
                                        targets.cameras, mesh.bounds, targets.lights, k)}
            target_images = pool_views(targets.images, k)
        summary.update(image_scores(images, target_images, fitted), variant=image_term.variant,
                       z_da=z_fit[0].tolist(), image_resolution=list(target_images.shape[-2:]))
        tile = lambda x: np.repeat(np.repeat(chw_to_uint8(x), k, 0), k, 1)  # noqa: E731  (the sheet's tile size)
        for i, row in enumerate(rows):
            row += [tile(target_images[i]), tile(images["start"][i]), tile(images["end"][i])]
        columns += ["target image", f"NGP ({image_term.variant}), start", "NGP, fitted"]
    own = fitted // 2 if config.mirror else fitted  # with --mirror the second half of the fitted views are mirror images

    def label(i: int) -> str:
        kind = " (held out)" if i >= fitted else f" (view {i - own} mirrored)" if i >= own else ""
        return f"view {i}{kind}, IoU {ious[i]:.3f}"

    save_png(out / "sheet.png", labelled_grid(rows, [label(i) for i in range(n)], columns))
    if frames:
        save_animation(out / "progress.gif", frames, fps=6)
    write_json(out / "fit.json", summary)
    chamfer = (f"Chamfer-L2 to the true shape {summary['chamfer_start']:.5f} → {summary['chamfer_end']:.5f}; "
               if truth is not None else "")
    write_text(out / "report.md", f"# fit-shape: {summary['shape_id']}\n\n{fitted} of {n} views fitted "
               f"({'their coverage (alpha)' if targets.coverage is not None else 'binary masks'}), "
               f"{summary['steps']} vertex steps"
               + (f"; loss {summary['loss_start']:.5f} → {summary['loss_end']:.5f}" if history else "") + f"; {chamfer}"
               f"mask IoU {summary['mask_iou_fitted']:.3f} on the fitted views"
               + (f", {summary['mask_iou_held_out']:.3f} on the held-out ones" if config.held_out else "")
               + (_image_sentence(summary) if image_term is not None else "")
               + ".\n\n![curves](curves.png)\n\n![target and fit per view](sheet.png)\n"
               + ("\n![progress](progress.gif)\n" if frames else ""))
    log(f"fit-shape: wrote {out / f'fit.{config.mesh_format}'}, {out / 'report.md'}")
    return summary


def image_scores(images: dict[str, torch.Tensor], target: torch.Tensor, fitted: int) -> dict[str, float | None]:
    """PSNR (dB) and FLIP of the sRGB images (whole image, clipped to [0, 1]) against the targets, at
    the start and the end of the fit, averaged over the fitted and over the held-out views."""
    from ngp_mi.eval.metrics import flip, psnr

    srgb = lambda x: linear_to_srgb(np.clip(x.permute(1, 2, 0).numpy(), 0, 1))  # noqa: E731
    scores: dict[str, float | None] = {}
    for when, image in images.items():
        per_view = [(psnr(srgb(t), srgb(i)), flip(srgb(t), srgb(i))[0]) for t, i in zip(target, image)]
        for part, views in (("fitted", per_view[:fitted]), ("held_out", per_view[fitted:])):
            scores[f"psnr_{part}_{when}"] = float(np.mean([p for p, _ in views])) if views else None
            scores[f"flip_{part}_{when}"] = float(np.mean([f for _, f in views])) if views else None
    return scores


def _image_sentence(summary: dict[str, Any]) -> str:
    part = "held_out" if summary["psnr_held_out_end"] is not None else "fitted"
    return (f"; NGP's image ({summary['variant']}) on the {part.replace('_', '-')} views: PSNR "
            f"{summary[f'psnr_{part}_start']:.2f} → {summary[f'psnr_{part}_end']:.2f} dB, FLIP "
            f"{summary[f'flip_{part}_start']:.3f} → {summary[f'flip_{part}_end']:.3f}")


def _write_mesh(path: Path, mesh: TriangleMesh) -> None:
    import trimesh

    if not np.isfinite(mesh.vertices).all():
        raise RuntimeError(f"fit-shape: refusing to write {path}: the mesh has non-finite vertices")
    with atomic_path(path) as tmp:
        trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(tmp, file_type=path.suffix[1:])


def _plot(phases: list[tuple[str, list[dict[str, float]]]], path: Path) -> None:
    """The named loss terms over the steps of the phases that ran, one after the other, the phases'
    boundaries marked."""
    import matplotlib  # only the curves need it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    history, bounds = [], []
    for name, steps in phases:
        if steps:
            history += [{**h, "step": h["step"] + len(history)} for h in steps]
            bounds.append((len(history), name))
    steps = [h["step"] for h in history]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name in [k for k in ("total", "mask", "depth", "image", "free") if any(k in h for h in history)]:
        ax.semilogy(steps, [max(h[name], 1e-12) if name in h else float("nan") for h in history], label=name)
    for (end, name), (_, following) in zip(bounds, bounds[1:]):
        ax.axvline(end + 0.5, color="grey", linestyle=":")
        ax.annotate(f"{name} | {following}", (end + 0.5, 1.0), xycoords=("data", "axes fraction"), fontsize=7,
                    ha="center", va="bottom", color="grey")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
