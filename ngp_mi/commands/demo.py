"""`make demo`: ``outputs/demo/index.html``, NGP under every handle, and the path-traced references.

For each NGP model (the shipped ``chair`` and ``car``, or the folders given), one section per handle,
each image labelled with what changed (:func:`ngp_sections`): a camera orbit, a light orbit (count,
colour and position change), appearance and shape sweeps, an exemplar transfer (E_da of a reference
albedo map, and its code fitted to that map), the variants NGP / NGP-BP / NGP-plus side by side and every intermediate map. Then
one inverse-rendering fit (:func:`fit_section`: a chair recovered from 8 views through Π_v), and
the references, path traced by Mitsuba:

1. ``views.png`` — a procedural chair path traced from views drawn from the paper's camera
   distribution, under the paper's 4-light overhead rig (``views.json``: cameras and lights).
2. ``chair.png``, ``car.png`` — 16 samples of each procedural family, to show their variety.
"""

from __future__ import annotations

import html
import json
import math
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from ngp_mi.atomic import write_json, write_text
from ngp_mi.camera import Camera, ViewDistribution
from ngp_mi.data.sources import resolve_source
from ngp_mi.geometry.families import FAMILIES, generate
from ngp_mi.lights import DirectionalLight, Light, PointLight, lights_to_json, overhead_rig
from ngp_mi.models.pretrained import available
from ngp_mi.pipeline import NGP, EmptyShape, ExemplarView, NGPScene, display_maps
from ngp_mi.render.gbuffer import GBufferRenderer
from ngp_mi.render.preview import object_shapes, preview_sheet
from ngp_mi.render.scene import build_scene, render, set_sensor_camera
from ngp_mi.viz import chw_to_uint8, contact_sheet, labelled_grid, save_animation, save_png, to_uint8

FAMILY_VIEW = (15.0, 35.0)
FIT_STEPS = 30  # the exemplar transfer's fitted row (compare --exemplar-steps 30: the chairs' 40-image figures)


def family_sheet(family: str, out: str | Path, count: int = 16, resolution: int = 128, spp: int = 32,
                 first_seed: int = 0) -> Path:
    """Contact sheet of ``count`` consecutive seeds of ``family`` from one paper-range view."""
    objects = [generate(family, seed) for seed in range(first_seed, first_seed + count)]
    return save_png(out, preview_sheet(objects, Camera.orbit(*FAMILY_VIEW, resolution), spp=spp))


Figure = tuple[str, str]  # (file relative to the page, caption)


def light_orbit_lights(step: int, steps: int) -> list[Light]:
    """Frame ``step`` of the light orbit: 1 to 4 lights (the count grows through the orbit), each its
    own colour, turning round the object; the last one a point light."""
    colours = [(2.0, 1.6, 1.1), (0.8, 1.2, 2.2), (1.8, 0.7, 1.4), (1.3, 1.9, 0.9)]
    count = 1 + (4 * step) // steps
    lights: list[Light] = []
    for k in range(count):
        az = 2 * math.pi * (step / steps + k / count)
        if k == 3:
            lights.append(PointLight((1.2 * math.sin(az), 1.0, 1.2 * math.cos(az)), tuple(3 * c for c in colours[k])))
        else:
            lights.append(DirectionalLight((0.8 * math.sin(az), 0.6, 0.8 * math.cos(az)), colours[k]))
    return lights


def _reference_view(family: str, resolution: int) -> ExemplarView:
    """An albedo map to transfer, with its geometry: Mitsuba's G-buffer of another object of the family."""
    content = resolve_source(family if family in FAMILIES else "chair", 1, seed=7)[0].load()
    camera = Camera.orbit(10.0, -30.0, resolution)
    maps = GBufferRenderer(content.shapes, content.bounds, camera, ("albedo", "mask", "depth")).render(camera)
    tensor = lambda a: torch.from_numpy(np.ascontiguousarray(a)).float()  # noqa: E731
    return ExemplarView(tensor(maps["albedo"]).permute(2, 0, 1)[None], tensor(maps["depth"])[None, None],
                        tensor(maps["mask"])[None, None], camera, np.asarray(content.bounds))


def ngp_sections(ngp: NGP, name: str, out_dir: Path, resolution: int = 128, frames: int = 12,
                 log: Callable[[str], None] = print) -> list[tuple[str, list[Figure]]]:
    """NGP of one model under every handle; returns (section title, figures) with files under ``out_dir/name``."""
    folder = out_dir / name
    family = (ngp.card or {}).get("family") or name
    scene = NGPScene(ngp, resolution)
    rel = lambda file: f"{name}/{file}"  # noqa: E731
    done, start = [0], time.perf_counter()

    def step(what: str) -> None:
        done[0] += 1
        log(f"demo: {name} {what} ({done[0]} images, {done[0] / (time.perf_counter() - start):.1f}/s)")

    def set_base_shape() -> str:
        if ngp.shape_model is not None:
            for seed in range(16):  # the first latent whose shape is not empty
                try:
                    scene.set_shape(seed=seed).render()
                    return f"G_shape(z_s of seed {seed})"
                except EmptyShape:
                    continue
        scene.set_shape(mesh=generate(family if family in FAMILIES else "chair", 0).mesh())
        return f"the procedural {family} 0 (mesh)"

    shape_text = set_base_shape()
    scene.set_appearance(seed=0)
    sections: list[tuple[str, list[Figure]]] = []

    # camera orbit
    phis = np.linspace(-90.0, 90.0, frames)
    orbit = []
    for phi in phis:
        orbit.append(chw_to_uint8(scene.set_camera(theta=10.0, phi=float(phi)).render()["image"]))
        step("camera orbit")
    save_animation(folder / "camera_orbit.gif", orbit + orbit[-2:0:-1], fps=8)
    save_png(folder / "camera_orbit.png", labelled_grid([orbit[::2]], [shape_text], [f"φ {p:.0f}°" for p in phis[::2]]))
    sections.append((f"{name}: camera orbit (θ 10°, φ −90° … 90°)", [
        (rel("camera_orbit.gif"), "the camera goes round the object; everything else fixed"),
        (rel("camera_orbit.png"), "every other frame, labelled with the camera's azimuth")]))
    scene.set_camera(theta=10.0, phi=-30.0)

    # light orbit: count, colour and position change; only the shading re-runs
    light_frames, labels = [], []
    for k in range(frames):
        lights = light_orbit_lights(k, frames)
        light_frames.append(chw_to_uint8(scene.set_lights(lights).render()["image"]))
        labels.append(f"{len(lights)} light{'s' if len(lights) > 1 else ''}, {360 * k / frames:.0f}°")
        step("light orbit")
    scene.set_lights(overhead_rig())
    save_animation(folder / "light_orbit.gif", light_frames, fps=6)
    save_png(folder / "light_orbit.png", labelled_grid([light_frames[::2]], ["lights"], labels[::2]))
    sections.append((f"{name}: light orbit", [
        (rel("light_orbit.gif"), "1 to 4 coloured lights (the 4th a point light) turning round the object"),
        (rel("light_orbit.png"), "every other frame: light count and angle")]))

    # appearance and shape sweeps
    looks = []
    for seed in range(6):
        looks.append(chw_to_uint8(scene.set_appearance(seed=seed).render()["image"]))
        step("appearance")
    save_png(folder / "appearance.png", labelled_grid([looks], [shape_text], [f"z_da seed {s}" for s in range(6)]))
    figures = [(rel("appearance.png"), "the appearance latent z_da changes; shape, camera and lights fixed")]
    scene.set_appearance(seed=0)
    if ngp.shape_model is not None:
        shapes = []
        for seed in range(6):
            try:
                shapes.append(chw_to_uint8(scene.set_shape(seed=seed).render()["image"]))
            except EmptyShape:
                shapes.append(np.zeros((resolution, resolution, 3), np.uint8))
            step("shape")
        save_png(folder / "shapes.png", labelled_grid([shapes], ["z_da seed 0"], [f"z_s seed {s}" for s in range(6)]))
        figures.append((rel("shapes.png"), "the shape latent z_s changes (black: an empty shape); appearance fixed"))
        set_base_shape()
    sections.append((f"{name}: appearance and shape", figures))

    # exemplar transfer
    reference = _reference_view(family, resolution)
    rows = []
    for appearance in ({"exemplar": reference.albedo}, {"exemplar_view": reference, "fit_steps": FIT_STEPS}):
        transferred = scene.set_appearance(**appearance).render(maps=True)
        rows.append([chw_to_uint8(reference.albedo), display_maps(transferred)["albedo"],
                     chw_to_uint8(transferred["image"])])
        step("exemplar")
    save_png(folder / "exemplar.png", labelled_grid(
        rows, ["μ(E_da(exemplar))", f"z_da fitted, {FIT_STEPS} steps"],
        ["exemplar albedo (Mitsuba G-buffer)", "G_da", "NGP image"]))
    sections.append((f"{name}: exemplar transfer", [(rel("exemplar.png"),
                                                     "the appearance of a reference albedo map: the paper's handle "
                                                     "(E_da's code), then that code fitted to the exemplar on its own "
                                                     "geometry (pipeline.fit_appearance, beyond the paper)")]))
    scene.set_appearance(seed=0)

    # variants and every intermediate map
    added = [DirectionalLight((-0.6, 0.5, 0.8), (1.5, 0.6, 0.3))]
    scene.set_lights(overhead_rig(), added)
    variants = [v for v in ("ngp", "ngp_bp", "ngp_plus") if ngp.specular is not None or v == "ngp_bp"]
    tiles = []
    for variant in variants:
        tiles.append(chw_to_uint8(scene.set_variant(variant).render()["image"]))
        step("variant")
    save_png(folder / "variants.png", labelled_grid([tiles], [""], [
        {"ngp": "NGP: R_diff ⊕ G_sp^real", "ngp_bp": "NGP-BP: R_BP", "ngp_plus": "NGP-plus: + R_BP of an orange light"}[v]
        for v in variants]))
    scene.set_variant(variants[0])
    scene.set_lights(overhead_rig())
    maps = scene.render(maps=True)
    columns = ["coarse depth (Π_v)", "normals G_n", "albedo G_da", "R_diff / π", "G_sp^real", "image"]
    shown = display_maps(maps)
    row = [shown[name] for name in ("depth", "normal", "albedo", "shaded", "specular", "image")]
    save_png(folder / "maps.png", labelled_grid([row], [""], columns))
    step("maps")
    sections.append((f"{name}: variants and intermediate maps", [
        (rel("variants.png"), "the paper's variants side by side (same shape, view, appearance; the rig)"),
        (rel("maps.png"), "every intermediate map of NGP, left to right along the data flow")]))
    return sections


def fit_section(out_dir: Path, shape_model: object | None = None, resolution: int = 64, views: int = 8,
                held_out: int = 2, steps: int = 100, log=print) -> tuple[str, list[Figure]]:
    """Inverse rendering (``ngp-mi fit-shape``): a procedural chair (seed 7, not a training shape of
    the models) recovered from the masks and depths of ``views`` views, ``held_out`` more scored
    only; started from the shape prior's best latent when a model has one, else from a sphere."""
    from ngp_mi.commands.fit_shape import FitConfig, fit_shape
    from ngp_mi.data.render_dataset import DatasetConfig, render_dataset

    targets, fit_dir = out_dir / "fit" / "targets", out_dir / "fit"
    render_dataset(DatasetConfig(source="chair", num_shapes=1, views=views + held_out, resolution=resolution,
                                 channels=("depth", "mask"), seed=7), targets, progress=False)
    start = "zs" if shape_model is not None else "sphere"
    config = FitConfig(str(targets), held_out=held_out, steps=steps, start=start, zs_steps=20, frame_every=5)
    began = time.perf_counter()
    summary = fit_shape(config, fit_dir / "run", shape_model, log=lambda message: None)
    log(f"demo: fit-shape, {views} views, {steps} steps from {start}: {time.perf_counter() - began:.1f} s")
    prefix = "fit/run/"
    told = (f"Chamfer-L2 to the true chair {summary['chamfer_start']:.4f} → {summary['chamfer_end']:.4f}, mask IoU "
            f"{summary['mask_iou_held_out']:.3f} on {held_out} views the fit never saw")
    return (f"Inverse rendering: a chair recovered from {views} views through the differentiable Π_v (ngp-mi fit-shape)",
            [(prefix + "sheet.png", f"target vs fit per view, start: {'the shape prior' if start == 'zs' else 'a sphere'}; "
              + told), (prefix + "progress.gif", f"the silhouette over {steps} steps (blue target, orange fit)"),
             (prefix + "curves.png", "the named loss terms")])


def write_page(out_dir: Path, sections: Sequence[tuple[str, Sequence[Figure]]], note: str = "") -> Path:
    """``index.html``: one heading per section, each image with its caption."""
    body = "".join(
        f"<section><h2>{html.escape(title)}</h2>" + "".join(
            f'<figure><img src="{html.escape(src)}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>" for src, caption in figures) + "</section>\n"
        for title, figures in sections)
    page = ("<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>ngp-mi demo</title>"
            "<style>body{font-family:sans-serif;background:#202020;color:#ddd;margin:2em}"
            "figure{display:inline-block;margin:0 1em 1em 0;vertical-align:top}"
            "img{image-rendering:pixelated;max-width:100%}figcaption{font-size:0.9em;color:#aaa}"
            ".note{background:#332;padding:0.5em 1em}</style></head><body>"
            "<h1>Neural Graphics Pipeline on Mitsuba 3 / Dr.Jit — demo</h1>"
            + (f'<p class="note">{html.escape(note)}</p>' if note else "") + body + "</body></html>\n")
    return write_text(out_dir / "index.html", page)


def run_demo(out_dir: str | Path = "outputs/demo", models: Sequence[str] | None = None, resolution: int = 128,
             views: int = 12, spp: int = 64, seed: int = 0, family_count: int = 16, frames: int = 12,
             fit_steps: int = 100, log=print) -> Path:
    """Write the demo page and its images; returns the path of ``index.html``. ``models``: shipped
    model names or model folders (default: every shipped one)."""
    out_dir = Path(out_dir)
    models = list(models) if models is not None else available()
    sections: list[tuple[str, list[Figure]]] = []
    ngps = [NGP.pretrained(model) for model in models]
    for model, ngp in zip(models, ngps):
        sections += ngp_sections(ngp, Path(model).name, out_dir, resolution, frames, log)
    sections.append(fit_section(out_dir, next((n.shape_model for n in ngps if n.shape_model is not None), None),
                                steps=fit_steps, log=log))
    reference_sheet(out_dir, resolution, views, spp, seed, family_count, log)
    sections.append(("Reference: a procedural chair path traced by Mitsuba from the paper's view distribution", [
        ("views.png", f"{views} views θ ∈ [0°, 20°], φ ∈ [−90°, 90°], the 4-light overhead rig, {spp} spp")]))
    sections.append(("Reference: the procedural families the models learn from", [
        ("chair.png", f"{family_count} procedural chairs with their part materials"),
        ("car.png", f"{family_count} procedural cars")]))
    note = "" if models else ("No NGP model is shipped in this install yet (README, “Shipped models”): this page shows "
                              "the path-traced references only. `ngp-mi demo --model FOLDER` shows NGP of a model "
                              "folder written by `ngp-mi export-model`.")
    page = write_page(out_dir, sections, note)
    log(f"demo: wrote {page}")
    return page


def reference_sheet(out_dir: str | Path, resolution: int = 128, views: int = 12, spp: int = 64, seed: int = 0,
                    family_count: int = 16, log=print) -> Path:
    """The path-traced references: ``views.png`` (+ ``views.json``), ``chair.png``, ``car.png``."""
    out_dir = Path(out_dir)
    obj = generate("chair", seed)
    lights = overhead_rig()
    cameras = ViewDistribution().sample(views, seed=seed, resolution=resolution)
    scene = build_scene(cameras[0], object_shapes(obj), lights, integrator={"type": "path", "max_depth": 4},
                        spp=spp, seed=seed)
    sensor = scene.sensors()[0]
    tiles, labels, start = [], [], time.perf_counter()
    for i, camera in enumerate(cameras):
        set_sensor_camera(sensor, camera)
        tiles.append(to_uint8(render(scene, seed=seed + i)))
        labels.append(f"th={camera.theta_deg:.0f} ph={camera.phi_deg:.0f}")
        rate = (i + 1) / (time.perf_counter() - start)
        log(f"demo: view {i + 1}/{views}  {rate:.1f} views/s  ETA {(views - i - 1) / rate:.1f} s")
    sheet = save_png(out_dir / "views.png", contact_sheet(tiles, labels, columns=4))
    write_json(out_dir / "views.json", {
        "object": obj.id, "params": obj.params, "resolution": resolution, "spp": spp, "seed": seed,
        "cameras": [c.to_dict() for c in cameras], "lights": json.loads(lights_to_json(lights))["lights"],
    })
    log(f"demo: wrote {sheet}")
    for family in ("chair", "car"):
        path = family_sheet(family, out_dir / f"{family}.png", count=family_count, resolution=resolution,
                            spp=max(1, spp // 2))
        log(f"demo: wrote {path}")
    return sheet
