"""``ngp-mi compare``: deferred / neural shading against physically based references, timed.

For every shape × view × light setup this renders, times and scores against the reference:

* **reference** — Mitsuba path tracing (``path``, max depth 6) of the shape's principled materials
  at ``reference_spp``;
* **path tracing** at a ladder of lower spp (other seeds than the reference);
* **R_diff** (k_d = 1) and **R_BP** (the paper's k_d, k_s, α) on the ground-truth G-buffer maps
  (render of the maps + shading), the deferred renderers of NGP;
* the effects the deferred renderers lack, as images of their own: ``direct`` (direct light with
  shadows, no interreflection) and ``direct_unshadowed`` (no shadows either);
* with a trained ``train maps`` run (``maps_checkpoint``), NGP's images on generated maps (paper
  Sec. 5 and App. "NGP variants"): NGP-BP, NGP (R_diff ⊕ G_sp^real, when the run has the specular
  stage), NGP-plus (NGP under the overhead rig plus R_BP of the additional lights; light setup
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
import html
import json
import math
import statistics
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ngp_mi import backend
from ngp_mi.camera import Camera
from ngp_mi.data.render_dataset import DatasetConfig, derived_seed, view_cameras, view_lights
from ngp_mi.data.sources import resolve_source
from ngp_mi.eval.metrics import flip, psnr, ssim
from ngp_mi.lights import Light, overhead_rig
from ngp_mi.render.gbuffer import GBufferRenderer, maps_to_tensors
from ngp_mi.render.scene import build_scene, lights_to_mitsuba, render, set_sensor_camera
from ngp_mi.render.shading import shade
from ngp_mi.viz import contact_sheet, linear_to_srgb, save_png, to_uint8


@dataclasses.dataclass(frozen=True)
class CompareConfig:
    source: str = "chair"
    num_shapes: int = 3
    views: int = 2
    resolution: int = 128
    light_setups: tuple[str, ...] = ("rig", "random")
    spp_ladder: tuple[int, ...] = (1, 4, 16, 64, 256)
    reference_spp: int = 1024
    seed: int = 0
    k_d: float = 0.8
    k_s: float = 0.2
    alpha: float = 4.0
    maps_checkpoint: str | None = None  # a `train maps` run: adds NGP's variants and ablations
    inception_weights: str | None = None  # inception-2015-12-05.pt: adds FID / KID


METRICS = ("psnr_linear", "ssim_linear", "psnr_srgb", "ssim_srgb", "flip")
LIGHT_SETUPS = ("rig", "random", "rig+random")


def setup_lights(config: DatasetConfig, setup: str, shape_index: int, view: int) -> tuple[list[Light], list[Light]]:
    """(all lights, the lights beyond the overhead rig) of one light setup."""
    if setup not in LIGHT_SETUPS:
        raise ValueError(f"light setup must be one of {LIGHT_SETUPS}, got {setup!r}")
    if setup == "rig":
        return overhead_rig(), []
    extra = view_lights(dataclasses.replace(config, lights="random"), shape_index, view)
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
    import ngp_mi.render.direct_unshadowed  # noqa: F401  (registers the integrator)

    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    for setup in config.light_setups:
        setup_lights(DatasetConfig(source=config.source), setup, 0, 0)  # bad names fail before any work
    inception = None
    if config.inception_weights:
        from ngp_mi.eval.fid import InceptionFeatures

        inception = InceptionFeatures(config.inception_weights)
    items = resolve_source(config.source, config.num_shapes, config.seed)
    model = specular = None
    if config.maps_checkpoint:
        from ngp_mi.eval.maps_eval import load_model, load_specular

        model, specular = load_model(config.maps_checkpoint), load_specular(config.maps_checkpoint)
    images_by_method: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    rows: list[dict[str, Any]] = []
    sheets: list[str] = []
    for index, item in enumerate(items):
        content = item.load()
        dataset_like = DatasetConfig(source=config.source, views=config.views, resolution=config.resolution,
                                     seed=config.seed, lights="random")
        for view, camera in enumerate(view_cameras(dataset_like, index)):
            gbuffer = GBufferRenderer(content.shapes, content.bounds, camera, ("depth", "normal", "albedo", "mask"))
            for setup in config.light_setups:
                lights, extra = setup_lights(dataset_like, setup, index, view)
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
    summary = summarise(rows)
    if inception is not None:
        add_distribution_distances(summary, images_by_method, inception, log)
    (out / "results.json").write_text(json.dumps({"config": dataclasses.asdict(config), "rows": rows,
                                                  "summary": summary}, indent=1))
    plot_speed_accuracy(summary, out / "speed_accuracy.png")
    write_report(config, summary, sheets, out)
    log(f"compare: wrote {out / 'report.html'}")
    return summary


def add_distribution_distances(summary: list[dict[str, Any]], images: dict[str, list[tuple[np.ndarray, np.ndarray]]],
                               inception: Any, log=print) -> None:
    """FID and KID of each method's sRGB images against the reference images of the same views."""
    from ngp_mi.eval.metrics import fid_from_features, kernel_inception_distance

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
        set_sensor_camera(scene.sensors()[0], camera)
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

    def neural(variant: str) -> Callable[[], np.ndarray]:
        """One NGP variant (:func:`ngp_mi.pipeline.ngp_image`) on this view, from the ground-truth depth,
        with the appearance code μ(E_da(ground-truth albedo)) (the exemplar handle)."""
        from ngp_mi.pipeline import Constants, ngp_image

        def run() -> np.ndarray:
            t = maps_to_tensors(gbuffer.render(camera))
            with torch.no_grad():
                mu, _ = model.E_da(2 * t["albedo"] - 1)
            result = ngp_image(model, specular, t["depth"], t["mask"], camera, content.bounds, mu, lights, variant,
                               extra, Constants(config.k_d, config.k_s, config.alpha))
            return result["image"][0].permute(1, 2, 0).numpy()
        return run

    methods: list[tuple[str, str, Callable[[], np.ndarray]]] = [
        (f"path tracing {spp} spp", "path", physically_based(path, spp, seed + 1000 + spp)) for spp in config.spp_ladder]
    methods += [
        ("R_diff, k_d = 1 (GT maps)", "deferred", deferred("diffuse", k_d=1.0)),
        (f"R_BP, k_d {config.k_d}, k_s {config.k_s}, α {config.alpha:g} (GT maps)", "deferred",
         deferred("blinn_phong", k_d=config.k_d, k_s=config.k_s, alpha=config.alpha)),
        ("direct light + shadows, no interreflection", "effect",
         # Plain "direct": with emitter_samples > 1 Mitsuba 3.9.1 scales the image by that count when
         # the spp is given at render time (measured: 4x too bright with emitter_samples 4).
         physically_based({"type": "direct"}, max(16, config.reference_spp // 2), seed + 7)),
        ("direct light, no shadows (what R_* can model)", "effect",
         physically_based({"type": "direct_unshadowed"}, 16, seed + 8)),
    ]
    if model is not None:
        methods += [
            (f"NGP-BP: R_BP on generated maps (k_d {config.k_d}, k_s {config.k_s}, α {config.alpha:g})", "neural",
             neural("ngp_bp")),
            ("NGP w/o G_sp^real: R_diff on generated maps", "neural", neural("no_sp")),
        ]
    if model is not None and specular is not None:
        methods += [("NGP: R_diff ⊕ G_sp^real", "neural", neural("ngp")),
                    ("NGP w/o G_n: normals from the depth map", "neural", neural("no_gn")),
                    ("NGP w/o G_da: white albedo", "neural", neural("no_gda"))]
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
        labels.append(name.split(" (")[0][:22])
    error_tiles = [_magma(e) for e in errors]
    sheet = contact_sheet(tiles + error_tiles, labels + ["FLIP error"] * len(errors), columns=len(tiles))
    save_png(sheet_path, sheet)
    return rows, sheet_path.name, images


def _magma(error: np.ndarray) -> np.ndarray:
    from matplotlib import colormaps

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
            if key.split("_masked")[0] in METRICS:
                values = [r[key] for r in group if math.isfinite(r[key])]
                entry[key] = float(np.mean(values)) if values else float("inf")
        summary.append(entry)
    return summary


def plot_speed_accuracy(summary: list[dict[str, Any]], path: Path) -> None:
    """Time (log) against masked sRGB PSNR and FLIP: the path-tracing ladder as a curve, others as points."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    ladder = [s for s in summary if s["kind"] == "path"]
    for ax, key, label in ((axes[0], "psnr_srgb_masked", "PSNR (sRGB, object) dB ↑"),
                           (axes[1], "flip_masked", "FLIP (object) ↓")):
        ax.plot([s["median_ms"] for s in ladder], [s[key] for s in ladder], "o-", color="black", label="path tracing")
        for s in ladder:
            ax.annotate(f"{s['spp']} spp", (s["median_ms"], s[key]), textcoords="offset points", xytext=(4, 4), fontsize=8)
        for s, marker in zip([s for s in summary if s["kind"] in ("deferred", "effect", "neural")], "s^Dv*PXhpd<>"):
            ax.plot([s["median_ms"]], [s[key]], marker, markersize=8, label=s["method"])
        ax.set_xscale("log")
        ax.set_xlabel("time per image, ms (median)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[1].legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(config: CompareConfig, summary: list[dict[str, Any]], sheets: list[str], out: Path) -> None:
    b = backend.load()
    keys = ["median_ms"] + [f"{m}{suffix}" for suffix in ("", "_masked") for m in METRICS]
    keys += [k for k in ("fid", "kid") if any(k in s for s in summary)]
    head = ["method"] + [k.replace("median_ms", "median ms") for k in keys]
    rows = "\n".join(f"<tr><td>{html.escape(s['method'])}</td>" + "".join(f"<td>{_fmt(s.get(k, ''))}</td>" for k in keys)
                     + "</tr>" for s in summary)
    ref = next(s for s in summary if s["kind"] == "reference")
    if "fid" in keys:
        fid_note = (f"FID / KID: Inception-v3 pool3 features ({html.escape(str(config.inception_weights))}) of each "
                    "method's sRGB images against the reference images of the same views; KID is the unbiased "
                    "cubic-kernel MMD². With few images FID is strongly biased upwards (its covariances have "
                    "rank &lt; images): compare methods within this table only.")
    else:
        from ngp_mi.eval.fid import missing_weights_message

        fid_note = "FID / KID not computed: " + html.escape(missing_weights_message(None)) + "."
    images = "\n".join(f'<p>{html.escape(name)}</p><img src="images/{html.escape(name)}">' for name in sheets)
    text = f"""<!doctype html><html><head><meta charset="utf-8"><title>ngp-mi compare</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:auto}} table{{border-collapse:collapse;font-size:12px}}
td,th{{border:1px solid #ccc;padding:3px 6px;text-align:right}} td:first-child{{text-align:left}}</style></head><body>
<h1>Deferred shading vs path tracing</h1>
<p>{config.num_shapes} shapes of <code>{html.escape(config.source)}</code> × {config.views} views × lights
{', '.join(config.light_setups)} at {config.resolution}²; {b.variant}, {b.threads} threads, Mitsuba {b.mi.__version__}.
Reference: path tracing (max depth 6) at {config.reference_spp} spp ({_fmt(ref['median_ms'])} ms per image).</p>
<h2>Conventions</h2>
<ul><li>All images are linear RGB radiance. R_diff and R_BP are divided by π: R_diff with k_d = 1 equals the
radiance of a Lambertian surface of albedo I_d under the same lights, and R_BP uses the paper's constants
(k_d {config.k_d}, k_s {config.k_s}, α {config.alpha:g}).</li>
<li>No exposure or tone mapping; sRGB metrics apply the sRGB transfer function to values clipped to [0, 1].</li>
<li>PSNR uses peak 1; SSIM is scikit-image's (Gaussian σ 1.5); FLIP is NVIDIA's (LDR, 67 pixels per degree).
"_masked" averages over the object only (mask of the G-buffer); times are medians over images, after a warm-up.</li>
<li>Deferred times include rendering the G-buffer maps and shading them. "direct + shadows" and
"direct, no shadows" are physically based images without interreflection (and without shadows): the
differences to the reference measure what the deferred renderers cannot model.</li>
<li>Neural rows (with <code>--maps-checkpoint</code>): G_n and G_da of a trained run applied to the
ground-truth depth of each view, with the appearance code taken from E_da of the ground-truth albedo
(the exemplar handle). NGP-BP: R_BP under the setup's lights. NGP: R_diff / π ⊕ G_sp^real (added in linear
radiance, on the object; G_sp^real sees the diffuse image under the training rig, its input domain, so its
highlights do not follow other lights, as the paper notes). NGP-plus (setup rig+random only): NGP under the rig
plus R_BP / π of the added lights. Ablations as in the paper: w/o G_n uses normals computed from the depth map,
w/o G_da a white albedo, w/o G_sp^real the diffuse image alone. NGP, NGP-plus and two ablations need a run
with the specular stage.</li>
<li>{fid_note}</li></ul>
<h2>Results</h2><table><tr>{''.join(f'<th>{html.escape(h)}</th>' for h in head)}</tr>
{rows}</table>
<h2>Speed against accuracy</h2><img src="speed_accuracy.png" width="1100">
<h2>Images (top: renders; bottom: FLIP error against the reference)</h2>{images}
</body></html>"""
    (out / "report.html").write_text(text)


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return "∞" if math.isinf(value) else f"{value:.3f}" if abs(value) < 10 else f"{value:.1f}"
    return str(value)
