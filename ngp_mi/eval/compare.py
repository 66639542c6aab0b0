"""``ngp-mi compare``: deferred / neural shading against physically based references, timed.

For every shape × view × light setup this renders, times and scores against the reference:

* **reference** — Mitsuba path tracing (``path``, max depth 6) of the shape's principled materials
  at ``reference_spp``;
* **path tracing** at a ladder of lower spp (other seeds than the reference);
* **R_diff** (k_d = 1) and **R_BP** (the paper's k_d, k_s, α) on the ground-truth G-buffer maps
  (render of the maps + shading), the deferred renderers of NGP;
* the effects the deferred renderers lack, as images of their own: ``direct`` (direct light with
  shadows, no interreflection) and ``direct_unshadowed`` (no shadows either);
* with trained map networks (``maps_checkpoint``: a ``train maps`` run, a model folder or a
  shipped name), NGP's images on generated maps (paper Sec. 5 and App. "NGP variants"): NGP-BP,
  NGP (R_diff ⊕ G_sp^real, when there is a specular stage), NGP-plus (NGP under the overhead rig plus R_BP of the additional lights; light setup
  ``rig+random``), and the ablations w/o G_n, w/o G_da and w/o G_sp^real;
* FID and KID of every method's images against the reference images, when the Inception weights
  are given (``inception_weights``, see :mod:`ngp_mi.eval.fid`).

Light setups: ``rig`` (the 4 overhead lights of training), ``random`` (1–4 random lights) and
``rig+random`` (the rig plus random additional lights, the NGP-plus use case).

Radiometric conventions (stated in the report): all images are linear RGB radiance; the
Blinn-Phong images are divided by π, since R_diff with k_d = 1 is π times the radiance of a
Lambertian surface under the same lights (``render.shading``); no exposure or tone mapping is
applied except the sRGB transfer function for sRGB metrics and pictures. Metrics are computed on
the full frame and on the object only (mask from the G-buffer).
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from ngp_mi.atomic import write_json
from ngp_mi.camera import Camera
from ngp_mi.data.sources import resolve_source
from ngp_mi.data.views import derived_seed, random_lights, view_cameras
from ngp_mi.eval.fid import InceptionFeatures
from ngp_mi.eval.metrics import (added_light_placement, fid_from_features, flip, kernel_inception_distance,
                                 nyquist_power_fraction, psnr, ssim)
from ngp_mi.eval.report import COMPARE_METRICS, SPECULAR_METRICS, plot_speed_accuracy, write_compare_report
from ngp_mi.lights import Light, overhead_rig
from ngp_mi.models.pretrained import load_ngp_networks, trained_source
from ngp_mi.nets.networks import check_image_size
from ngp_mi.pipeline import fit_appearance, ngp_image
from ngp_mi.render.gbuffer import GBufferRenderer, maps_to_tensors
from ngp_mi.render.scene import build_scene, lights_to_mitsuba, render
from ngp_mi.render.shading import Constants, shade
from ngp_mi.viz import contact_sheet, linear_to_srgb, save_png, to_uint8


@dataclasses.dataclass(frozen=True)
class CompareConfig:
    source: str | None = None  # None: the family the map networks trained on ([data] source), else chair
    num_shapes: int = 3
    views: int = 2
    resolution: int = 128
    light_setups: tuple[str, ...] = ("rig", "random")
    spp_ladder: tuple[int, ...] = (1, 4, 16, 64, 256)
    reference_spp: int = 1024
    seed: int = 0
    # R_BP's constants; None: the trained model's (with maps_checkpoint), else the paper's for the source's family
    constants: Constants | None = None
    maps_checkpoint: str | None = None  # a `train maps` run or a model: adds NGP's variants and ablations
    # Beyond the paper: also NGP with and without G_sp^real at z_da refined by this many steps on the
    # exemplar (:func:`ngp_mi.pipeline.fit_appearance`) beside μ(E_da)'s rows; 0: off
    exemplar_steps: int = 0
    inception_weights: str | None = None  # inception-2015-12-05.pt: adds FID / KID


METRICS = COMPARE_METRICS
NGP_METHOD, NO_SP_METHOD = "NGP: R_diff ⊕ G_sp^real", "NGP w/o G_sp^real: R_diff on generated maps"
FITTED = ", z_da fitted to the exemplar"  # suffix of the rows with exemplar_steps
LIGHT_SETUPS = ("rig", "random", "rig+random")


def check_light_setups(setups: Sequence[str]) -> None:
    for setup in setups:
        if setup not in LIGHT_SETUPS:
            raise ValueError(f"light setup must be one of {LIGHT_SETUPS}, got {setup!r}")


def setup_lights(setup: str, seed: int, shape_index: int, view: int) -> tuple[list[Light], list[Light]]:
    """(all lights, the lights beyond the overhead rig) of one light setup."""
    check_light_setups([setup])
    if setup == "rig":
        return overhead_rig(), []
    extra = random_lights(seed, shape_index, view)
    return (overhead_rig() + extra if setup == "rig+random" else extra), extra


def score(reference: np.ndarray, test: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """All metrics, full frame and masked (``*_masked``)."""
    ref_srgb, test_srgb = linear_to_srgb(reference), linear_to_srgb(test)
    out = {}
    for suffix, m in (("", None), ("_masked", mask)):
        out["psnr_linear" + suffix] = psnr(reference, test, m)
        out["ssim_linear" + suffix] = ssim(np.clip(reference, 0, 1), np.clip(test, 0, 1), m)
        out["psnr_srgb" + suffix] = psnr(ref_srgb, test_srgb, m)
        out["ssim_srgb" + suffix] = ssim(ref_srgb, test_srgb, m)
        out["flip" + suffix] = flip(ref_srgb, test_srgb, m)[0]
    return out


def _timed(fn: Callable[[], np.ndarray]) -> tuple[np.ndarray, float]:
    fn()  # warm-up: kernel compilation and caches are not what we compare
    start = time.perf_counter()
    image = fn()
    return image, time.perf_counter() - start


def run_compare(config: CompareConfig, out: str | Path, log=print) -> dict[str, Any]:
    """Render, time and score every method; write images, ``results.json`` and ``report.html``."""
    out = Path(out)
    check_light_setups(config.light_setups)  # bad names fail before any work
    if config.maps_checkpoint:
        check_image_size(config.resolution, config.resolution, "--res")
    (out / "images").mkdir(parents=True, exist_ok=True)
    inception = None
    if config.inception_weights:
        inception = InceptionFeatures(config.inception_weights)
    if config.source is None:  # a car model is scored on cars, not on the default chairs
        config = dataclasses.replace(config, source=trained_source(config.maps_checkpoint)
                                     if config.maps_checkpoint else "chair")
    items = resolve_source(config.source, config.num_shapes, config.seed)
    model = specular = None
    if config.maps_checkpoint:
        model, specular = load_ngp_networks(config.maps_checkpoint)
    if config.constants is None:
        config = dataclasses.replace(config, constants=model.config.constants if model is not None
                                     else Constants.of_family(config.source))
    images_by_method: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    rows: list[dict[str, Any]] = []
    sheets: list[str] = []
    for index, item in enumerate(items):
        content = item.load()
        for view, camera in enumerate(view_cameras(config.views, config.resolution, config.seed, index)):
            gbuffer = GBufferRenderer(content.shapes, content.bounds, camera, ("depth", "normal", "albedo", "mask"))
            for setup in config.light_setups:
                lights, extra = setup_lights(setup, config.seed, index, view)
                name = f"{item.id.replace('/', '_')}_v{view}_{setup.replace('+', '-')}"
                log(f"compare: {name}")
                rows_here, sheet, images = _compare_one(config, content, camera, gbuffer, lights, extra, derived_seed(
                    config.seed, index, view), out / "images" / f"{name}.png", model, specular)
                for row in rows_here:
                    row.update(shape=item.id, view=view, lights=setup)
                for method, pair in images.items():
                    images_by_method.setdefault(method, []).append(pair)
                rows.extend(rows_here)
                sheets.append(sheet)
    summary = add_equal_flip_times(summarise(rows))
    if inception is not None:
        add_distribution_distances(summary, images_by_method, inception, log)
    write_json(out / "results.json", {"config": dataclasses.asdict(config), "rows": rows, "summary": summary})
    plot_speed_accuracy(summary, out / "speed_accuracy.png")
    write_compare_report(config, summary, sheets, out)
    log(f"compare: wrote {out / 'report.html'}")
    return summary


def add_equal_flip_times(summary: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Beside every method that is not path tracing, the time path tracing needs for the same FLIP
    (the speed users trade against accuracy): ``path_ms_at_equal_flip``, interpolated log-log between
    the two rungs of the spp ladder whose FLIP brackets the method's, and ``speedup`` = that time /
    the method's. Outside the ladder it says so (``equal_flip_note``): a FLIP worse than the lowest
    rung's is reached by path tracing in at most that rung's time; one better than the highest rung's
    needs more than the ladder measured."""
    ladder = sorted(((s["median_ms"], s["flip"]) for s in summary if s["kind"] == "path" and math.isfinite(s["flip"])),
                    key=lambda point: point[1], reverse=True)  # FLIP falls as spp grows
    if not ladder:
        return summary
    for entry in summary:
        if entry["kind"] in ("path", "reference") or not math.isfinite(entry.get("flip", math.inf)):
            continue
        target = entry["flip"]
        if target >= ladder[0][1]:
            entry["path_ms_at_equal_flip"], entry["equal_flip_note"] = ladder[0][0], "at most (lowest spp of the ladder)"
        elif target < ladder[-1][1]:
            entry["path_ms_at_equal_flip"], entry["equal_flip_note"] = ladder[-1][0], "more than (highest spp)"
        else:
            for (ms_a, flip_a), (ms_b, flip_b) in zip(ladder, ladder[1:]):
                if flip_b <= target <= flip_a:
                    w = 0.0 if flip_a == flip_b else math.log(flip_a / target) / math.log(flip_a / flip_b)
                    entry["path_ms_at_equal_flip"] = math.exp((1 - w) * math.log(ms_a) + w * math.log(ms_b))
                    entry["equal_flip_note"] = "interpolated"
                    break
        entry["speedup"] = entry["path_ms_at_equal_flip"] / entry["median_ms"] if entry["median_ms"] > 0 else math.inf
    return summary


def add_distribution_distances(summary: list[dict[str, Any]], images: dict[str, list[tuple[np.ndarray, np.ndarray]]],
                               inception: Any, log=print) -> None:
    """FID and KID of each method's sRGB images against the reference images of the same views."""
    reference_features: dict[int, np.ndarray] = {}  # per reference image (methods share them)
    for entry in summary:
        pairs = images.get(entry["method"])
        if not pairs or len(pairs) < 2:
            continue
        log(f"compare: FID / KID of {entry['method']} ({len(pairs)} images)")
        new = [r for r, _ in pairs if id(r) not in reference_features]
        if new:
            reference_features.update(zip(map(id, new), inception([linear_to_srgb(r) for r in new])))
        reference = np.stack([reference_features[id(r)] for r, _ in pairs])
        features = inception([linear_to_srgb(t) for _, t in pairs])
        entry["fid"] = fid_from_features(reference, features)
        entry["kid"] = kernel_inception_distance(reference, features)


def _compare_one(config: CompareConfig, content: Any, camera: Camera, gbuffer: GBufferRenderer, lights: list[Light],
                 extra: list[Light], seed: int, sheet_path: Path, model: Any = None, specular: Any = None,
                 ) -> tuple[list[dict[str, Any]], str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    scene_dict = {**content.shapes, **lights_to_mitsuba(lights)}

    def physically_based(integrator: dict, spp: int, render_seed: int) -> Callable[[], np.ndarray]:
        scene = build_scene(camera, scene_dict, (), integrator, spp=spp)
        return lambda: render(scene, seed=render_seed)[..., :3]

    path = {"type": "path", "max_depth": 6}
    reference, reference_time = _timed(physically_based(path, config.reference_spp, seed))
    maps = gbuffer.render(camera)
    mask = maps["mask"]

    def deferred(mode: str, **constants: float) -> Callable[[], np.ndarray]:
        def run() -> np.ndarray:
            t = maps_to_tensors(gbuffer.render(camera))
            with torch.no_grad():
                image = shade(t["normal"], t["albedo"], t["mask"], lights, camera, mode=mode, **constants)
            return image[0].permute(1, 2, 0).numpy() / math.pi
        return run

    def neural(variant: str, fit_steps: int = 0) -> Callable[[], np.ndarray]:
        """One NGP variant (:func:`ngp_mi.pipeline.ngp_image`) on this view, from the ground-truth depth,
        with the appearance code μ(E_da(ground-truth albedo)) (the exemplar handle), refined by
        ``fit_steps`` steps on it (:func:`~ngp_mi.pipeline.fit_appearance`; timed with the rest)."""
        def run() -> np.ndarray:
            t = maps_to_tensors(gbuffer.render(camera))
            z_da = fit_appearance(model, t["albedo"], t["depth"], t["mask"], camera, content.bounds, fit_steps)
            with torch.no_grad():
                result = ngp_image(model, specular, t["depth"], t["mask"], camera, content.bounds, z_da, lights,
                                   variant, extra, config.constants)
            return result["image"][0].permute(1, 2, 0).numpy()
        return run

    methods: list[tuple[str, str, Callable[[], np.ndarray]]] = [
        (f"path tracing {spp} spp", "path", physically_based(path, spp, seed + 1000 + spp)) for spp in config.spp_ladder]
    c = config.constants
    methods += [
        ("R_diff, k_d = 1 (GT maps)", "deferred", deferred("diffuse", k_d=1.0)),
        (f"R_BP, k_d {c.k_d}, k_s {c.k_s}, α {c.alpha:g} (GT maps)", "deferred",
         deferred("blinn_phong", k_d=c.k_d, k_s=c.k_s, alpha=c.alpha)),
        ("direct light + shadows, no interreflection", "effect",
         # Plain "direct": with emitter_samples > 1 Mitsuba 3.9.1 scales the image by that count when
         # the spp is given at render time (measured: 4x too bright with emitter_samples 4).
         physically_based({"type": "direct"}, max(16, config.reference_spp // 2), seed + 7)),
        ("direct light, no shadows (what R_* can model)", "effect",
         physically_based({"type": "direct_unshadowed"}, 16, seed + 8)),
    ]
    if model is not None:
        methods += [
            (f"NGP-BP: R_BP on generated maps (k_d {c.k_d}, k_s {c.k_s}, α {c.alpha:g})", "neural",
             neural("ngp_bp")),
            (NO_SP_METHOD, "neural", neural("no_sp")),
        ]
    if model is not None and specular is not None:
        methods += [(NGP_METHOD, "neural", neural("ngp")),
                    ("NGP w/o G_n: normals from the depth map", "neural", neural("no_gn")),
                    ("NGP w/o G_da: white albedo", "neural", neural("no_gda"))]
        if config.exemplar_steps > 0:
            methods += [(NO_SP_METHOD + FITTED, "neural", neural("no_sp", config.exemplar_steps)),
                        (NGP_METHOD + FITTED, "neural", neural("ngp", config.exemplar_steps))]
        if extra and len(extra) < len(lights):
            methods.append(("NGP-plus: NGP under the rig + R_BP of the added lights", "neural", neural("ngp_plus")))
    rows = [{"method": "reference", "kind": "reference", "seconds": reference_time, "spp": config.reference_spp}]
    tiles, errors, labels = [to_uint8(reference)], [np.zeros_like(mask)], ["reference"]
    images: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, kind, fn in methods:
        image, seconds = _timed(fn)
        images[name] = (reference, image)
        scores = score(reference, image, mask)
        row = {"method": name, "kind": kind, "seconds": seconds, **scores}
        if kind == "path":
            row["spp"] = int(name.split()[2])
        rows.append(row)
        tiles.append(to_uint8(image))
        errors.append(flip(linear_to_srgb(reference), linear_to_srgb(image))[1])
        # the sheet's tiles are narrow: a fitted row keeps its method's head and says so
        labels.append((name.removesuffix(FITTED).split(":")[0] + ", fitted z_da")[:22] if name.endswith(FITTED)
                      else name.split(" (")[0][:22])
    error_tiles = [_magma(e) for e in errors]
    error_labels = ["FLIP error"] * len(errors)
    if NGP_METHOD in images and NO_SP_METHOD in images:
        diffuse, composite = images[NO_SP_METHOD][1], images[NGP_METHOD][1]
        layer = composite - diffuse  # G_sp^real's light as NGP adds it
        placement = added_light_placement(reference, diffuse, composite, mask)
        next(r for r in rows if r["method"] == NGP_METHOD).update(
            {**{f"specular_{k}": v for k, v in placement.items()}, "specular_nyquist": nyquist_power_fraction(layer)})
        # the light G_sp^real adds above the light the reference has beyond the diffuse image, both ×4
        tiles.append(to_uint8(np.clip(4 * layer, 0, 1)))
        error_tiles.append(to_uint8(np.clip(4 * (reference - diffuse), 0, 1)))
        labels.append("G_sp^real adds, x4")
        error_labels.append("ref - w/o G_sp, x4")
    sheet = contact_sheet(tiles + error_tiles, labels + error_labels, columns=len(tiles))
    save_png(sheet_path, sheet)
    return rows, sheet_path.name, images


def _magma(error: np.ndarray) -> np.ndarray:
    from matplotlib import colormaps  # ~0.5 s to import: only when sheets are drawn

    return (colormaps["magma"](np.clip(error, 0, 1))[..., :3] * 255).astype(np.uint8)


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per method: median seconds and mean of every metric over images."""
    order, by_method = [], {}
    for row in rows:
        if row["method"] not in by_method:
            order.append(row["method"])
            by_method[row["method"]] = []
        by_method[row["method"]].append(row)
    summary = []
    for method in order:
        group = by_method[method]
        entry = {"method": method, "kind": group[0]["kind"], "images": len(group),
                 "median_ms": 1e3 * statistics.median(r["seconds"] for r in group)}
        if "spp" in group[0]:
            entry["spp"] = group[0]["spp"]
        for key in group[0]:
            if key.split("_masked")[0] in METRICS or key in SPECULAR_METRICS:
                values = [r[key] for r in group if math.isfinite(r[key])]
                entry[key] = float(np.mean(values)) if values else float("inf")
        summary.append(entry)
    return summary
