"""``ngp-mi generate``: NGP images of sampled shapes or a user mesh, every intermediate map, sweeps of
every handle as labelled contact sheets (and orbit animations), and a report.

Sweeps (:class:`Sweeps`), each a sheet ``sweeps/<name>.png`` whose rows are the shapes and whose
columns say what changed: a camera orbit (φ over the paper's range, −90°…90°), a light orbit (one
white directional light going round), appearance seeds, light counts (the first k lights of the
overhead rig); shape seeds and an interpolation between two latents (z_s, or z_da with a mesh) are one
row each. ``animate`` adds a looping GIF of each orbit. Every stage result is kept by
:class:`ngp_mi.pipeline.NGPScene`, so a light orbit re-runs only the shading.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from ngp_mi.atomic import write_json, write_text
from ngp_mi.geometry.loaders import load_mesh
from ngp_mi.lights import DirectionalLight, Light, lights_to_json, overhead_rig
from ngp_mi.pipeline import NGP, EmptyShape, ExemplarView, NGPScene, display_maps, exemplar_image
from ngp_mi.viz import chw_to_uint8, labelled_grid, save_animation, save_png


@dataclasses.dataclass(frozen=True)
class Sweeps:
    """What ``generate`` varies beyond its views (0 / empty: not swept)."""

    orbit_camera: int = 0  # views on the orbit at the first view's elevation
    orbit_light: int = 0  # positions of one light going round the object
    appearance_seeds: tuple[int, ...] = ()
    shape_seeds: tuple[int, ...] = ()
    light_count: tuple[int, ...] = ()  # the first k lights of the overhead rig
    interpolate: tuple[int, int] | None = None  # two seeds: z_s (z_da with a mesh) slerped between them
    steps: int = 5
    animate: bool = False  # a GIF of each orbit

    def __post_init__(self) -> None:
        for name in ("orbit_camera", "orbit_light"):
            if getattr(self, name) < 0:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 0, got {getattr(self, name)}")
        if self.steps < 2:
            raise ValueError(f"--steps must be >= 2, got {self.steps}")
        bad = [k for k in self.light_count if not 1 <= k <= 4]
        if bad:
            raise ValueError(f"--light-count takes counts of 1 to 4 (the overhead rig's lights), got {bad}")


def orbit_light(step: int, steps: int, irradiance: float = 1.5, elevation_deg: float = 40.0) -> DirectionalLight:
    """A white directional light at ``step`` of ``steps`` positions round the object."""
    az, el = 2 * math.pi * step / steps, math.radians(elevation_deg)
    return DirectionalLight((math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)),
                            (irradiance,) * 3)


def generate(maps_run: str | Path | None, out: str | Path, shape_run: str | Path | None = None,
             mesh_path: str | None = None, model: str | None = None,
             num: int = 4, seed: int = 0, views: Sequence[tuple[float, float]] = ((10.0, -30.0), (10.0, 30.0)),
             resolution: int = 128, lights: Sequence[Light] | None = None, added_lights: Sequence[Light] = (),
             variant: str = "ngp", exemplar: str | None = None, exemplar_view: str | None = None,
             exemplar_item: int = 0, fit_steps: int = 30, sweeps: Sweeps = Sweeps(),
             command: Sequence[str] | None = None, log: Callable[[str], None] = print) -> dict[str, Any]:
    """``ngp-mi generate``: ``num`` shapes (z_s of ``seed`` …, or the user's mesh) × ``views`` (θ, φ in
    degrees) of the networks of ``maps_run`` (+ ``shape_run``) or of a shipped ``model`` (``chair``,
    ``car`` or a model folder; the default when no run is named is ``chair``); writes ``images/*.png``, ``sheet.png`` (depth, normals, albedo, specular, image per
    row), the ``sweeps`` (``sweeps/*.png``, ``*.gif``), ``generate.json`` (the settings and
    ``command`` that re-run it) and ``report.md``. Every shape takes one appearance code: μ(E_da) of
    the albedo image ``exemplar`` (the paper's handle), or the code fitted in ``fit_steps`` steps to view
    ``exemplar_item`` of the ``render-dataset`` folder ``exemplar_view`` (its albedo on its own geometry,
    :func:`ngp_mi.pipeline.fit_appearance`); without either, z_da of ``seed`` + k for shape k."""
    if exemplar and exemplar_view:
        raise ValueError("generate: give --exemplar (an albedo image) or --exemplar-view (a render-dataset folder), "
                         "not both")
    if maps_run and model:
        raise ValueError("generate: give --maps-run (training runs) or --model (a shipped model), not both")
    if maps_run is None:
        ngp = NGP.pretrained(model or "chair")
        if ngp.shape_model is None and not mesh_path:
            raise ValueError(f"generate: the model {model or 'chair'!r} has no shape prior; give a --mesh")
    else:
        if not mesh_path and not shape_run:
            raise ValueError("generate: give a `train shape` run (--shape-run) to sample shapes, or a --mesh")
        ngp = NGP(maps_run, shape_run if mesh_path is None else None)
    if sweeps.shape_seeds and mesh_path:
        raise ValueError("generate: --shape-seeds samples shapes: give --shape-run instead of --mesh")
    out = Path(out)
    lights = list(lights) if lights is not None else overhead_rig()
    scene = NGPScene(ngp, resolution, variant).set_lights(lights, added_lights)
    z_exemplar = None
    if exemplar:
        z_exemplar = ngp.appearance(exemplar=exemplar_image(exemplar, resolution))
    elif exemplar_view:
        z_exemplar = ngp.appearance(view=ExemplarView.from_dataset(exemplar_view, exemplar_item), fit_steps=fit_steps)
    shapes = _shapes(scene, mesh_path, seed, num, z_exemplar)
    (out / "images").mkdir(parents=True, exist_ok=True)
    rows, labels, records, skipped = [], [], [], {}
    for name, set_shape in list(shapes):
        set_shape()
        try:
            scene.render()
        except EmptyShape as exc:  # a latent whose shape has no inside: named, not fatal
            skipped[name] = str(exc)
            shapes.remove((name, set_shape))
            log(f"generate: skipped {name}: {exc}")
            continue
        for theta, phi in views:
            result = scene.set_camera(theta=theta, phi=phi).render(maps=True)
            stem = f"{name}_t{theta:g}_p{phi:g}"
            save_png(out / "images" / f"{stem}.png", _image(result))
            records.append({"shape": name, "theta": theta, "phi": phi, "file": f"images/{stem}.png"})
            rows.append(_tiles(result))
            labels.append(stem)
            log(f"generate: {stem}")
    if not rows:
        raise ValueError(f"generate: every shape was empty ({'; '.join(f'{k}: {v}' for k, v in skipped.items())})")
    names = ["coarse depth", "normals", "albedo", "specular", "image"]
    save_png(out / "sheet.png", labelled_grid(rows, labels, names))
    swept = _sweeps(scene, shapes, views[0], sweeps, seed, out, log)
    settings = {"maps_run": str(maps_run) if maps_run else None, "shape_run": str(shape_run) if shape_run else None,
                "model": None if maps_run else (model or "chair"), "mesh": mesh_path,
                "num": num, "seed": seed, "views": [list(v) for v in views], "variant": variant,
                "resolution": resolution, "lights": json.loads(lights_to_json(lights)),
                "added_lights": json.loads(lights_to_json(added_lights)), "exemplar": exemplar,
                "exemplar_view": str(exemplar_view) if exemplar_view else None, "exemplar_item": exemplar_item,
                "fit_steps": fit_steps, "sweeps": dataclasses.asdict(sweeps)}
    summary = {**settings, "command": list(command) if command else None, "images": records, "skipped": skipped,
               "sweep_files": swept,
               "stage_runs": dict(scene.stage_runs)}
    write_json(out / "generate.json", summary)
    write_text(out / "report.md", _report(settings, labels, names, swept, command))
    return summary


def _shapes(scene: NGPScene, mesh_path: str | None, seed: int, num: int,
            z_exemplar: torch.Tensor | None) -> list[tuple[str, Callable[[], None]]]:
    """(name, a function that sets that shape and its appearance on the scene) for each shape."""
    def setter(k: int, **shape: Any) -> Callable[[], None]:
        def apply() -> None:
            scene.set_shape(**shape)
            if z_exemplar is not None:
                scene.set_appearance(z_exemplar)
            else:
                scene.set_appearance(seed=seed + k)
        return apply

    if mesh_path:
        return [("mesh", setter(0, mesh=load_mesh(mesh_path)))]  # loaded once: the scene keeps its projection
    return [(f"z{seed + k}", setter(k, seed=seed + k)) for k in range(num)]


def _sweeps(scene: NGPScene, shapes: list[tuple[str, Callable[[], None]]], view: tuple[float, float], sweeps: Sweeps,
            seed: int, out: Path, log: Callable[[str], None]) -> dict[str, str]:
    """Render every requested sweep; returns {sweep name: file}."""
    theta, phi = view
    base_lights, added = scene.lights, scene.added_lights
    files: dict[str, str] = {}

    def sheet(name: str, columns: list[str], row_of: Callable[[], list[np.ndarray]], per_shape: bool = True,
              animate: bool = False) -> None:
        rows, names = [], []
        for shape_name, set_shape in (shapes if per_shape else shapes[:1]):
            set_shape()
            rows.append(row_of())
            names.append(shape_name if per_shape else "")
        files[name] = f"sweeps/{name}.png"
        save_png(out / files[name], labelled_grid(rows, names, columns))
        if animate and sweeps.animate:
            frames = rows[0] + rows[0][-2:0:-1]  # there and back: the loop has no jump
            files[f"{name}_animation"] = f"sweeps/{name}.gif"
            save_animation(out / files[f"{name}_animation"], frames, fps=8)
        log(f"generate: sweep {name} ({len(rows)} x {len(columns)})")

    if sweeps.orbit_camera:
        phis = np.linspace(-90.0, 90.0, sweeps.orbit_camera) if sweeps.orbit_camera > 1 else [phi]
        sheet("orbit_camera", [f"φ {p:.0f}°" for p in phis],
              lambda: [_image(scene.set_camera(theta=theta, phi=float(p)).render()) for p in phis], animate=True)
    scene.set_camera(theta=theta, phi=phi)
    if sweeps.orbit_light:
        n = sweeps.orbit_light
        lights_of = [[orbit_light(k, n)] for k in range(n)]
        sheet("orbit_light", [f"light at {360 * k / n:.0f}°" for k in range(n)],
              lambda: [_image(scene.set_lights(ls, added).render()) for ls in lights_of], animate=True)
        scene.set_lights(base_lights, added)
    if sweeps.light_count:
        sheet("light_count", [f"{k} light{'s' if k > 1 else ''}" for k in sweeps.light_count],
              lambda: [_image(scene.set_lights(overhead_rig()[:k], added).render()) for k in sweeps.light_count])
        scene.set_lights(base_lights, added)
    if sweeps.appearance_seeds:
        sheet("appearance", [f"z_da seed {s}" for s in sweeps.appearance_seeds],
              lambda: [_image(scene.set_appearance(seed=s).render()) for s in sweeps.appearance_seeds])
    if sweeps.shape_seeds:
        def shape_row() -> list[np.ndarray]:
            return [_render_or_blank(scene.set_shape(seed=s).set_appearance(seed=seed)) for s in sweeps.shape_seeds]
        sheet("shapes", [f"z_s seed {s}" for s in sweeps.shape_seeds], shape_row, per_shape=False)
    if sweeps.interpolate:
        a, b = sweeps.interpolate
        ts = np.linspace(0.0, 1.0, sweeps.steps)
        if scene.ngp.shape_model is not None:
            what, move = "z_s", lambda t: scene.interpolate_shapes(a, b, float(t))
        else:
            what, move = "z_da", lambda t: scene.interpolate_appearance(a, b, float(t))
        sheet("interpolation", [f"{what} {a}→{b}, t {t:.2f}" for t in ts],
              lambda: [_render_or_blank(move(t)) for t in ts], per_shape=what == "z_da")
    return files


def _render_or_blank(scene: NGPScene) -> np.ndarray:
    """The image, or a black tile where G_shape gives an empty shape (a sweep keeps its columns)."""
    try:
        return _image(scene.render())
    except EmptyShape:
        return np.zeros((scene.camera.height, scene.camera.width, 3), np.uint8)


def _image(result: dict[str, torch.Tensor]) -> np.ndarray:
    return chw_to_uint8(result["image"])


def _report(settings: dict[str, Any], labels: list[str], names: list[str], swept: dict[str, str],
            command: Sequence[str] | None) -> str:
    networks = f"`{settings['maps_run']}`" if settings["maps_run"] else f"the shipped model `{settings['model']}`"
    prior = settings["shape_run"] or settings["model"]
    shapes = (f"`{settings['mesh']}`" if settings["mesh"] else
              f"G_shape of `{prior}`, z_s seeds {settings['seed']}…{settings['seed'] + settings['num'] - 1}")
    appearance = ("μ(E_da) of `{}`".format(settings["exemplar"]) if settings["exemplar"] else
                  "z_da fitted in {} steps to view {} of `{}`".format(settings["fit_steps"], settings["exemplar_item"],
                                                                     settings["exemplar_view"])
                  if settings["exemplar_view"] else "z_da ~ N(0, I), one per shape")
    added = f" + {len(settings['added_lights'])} added" if settings["added_lights"] else ""
    text = (f"# NGP images ({settings['variant']})\n\nMaps: {networks}; shapes: {shapes}; appearance: "
            f"{appearance}; {len(settings['lights'])} light(s){added}; {settings['resolution']}².\n\n"
            + (f"Re-run: `{' '.join(command)}`\n\n" if command else "")
            + "Rows: one view each (" + ", ".join(labels) + "); columns: " + ", ".join(names)
            + ".\n\n![sheet](sheet.png)\n")
    for name, file in swept.items():
        text += f"\n## {name.replace('_', ' ')}\n\n![{name}]({file})\n"
    return text


def _tiles(result: dict[str, torch.Tensor]) -> list[np.ndarray]:
    """One row of the sheet: coarse depth, normals, albedo, specular, image."""
    shown = display_maps(result)
    return [shown[name] for name in ("depth", "normal", "albedo", "specular", "image")]
