"""Reports people look at: the speed-accuracy plot and the HTML report of ``ngp-mi compare``.

All images in reports are written beside them (relative links), so a report folder can be moved
or served as it is.
"""

from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Any, Sequence

from ngp_mi import backend
from ngp_mi.atomic import write_text
from ngp_mi.eval.fid import missing_weights_message

COMPARE_METRICS = ("psnr_linear", "ssim_linear", "psnr_srgb", "ssim_srgb", "flip")
# G_sp^real's light against the reference's excess over the diffuse image (added_light_placement), and
# its hue against the excess's, and the share of its power in a 2-pixel checkerboard
# (nyquist_power_fraction): NGP's row only
SPECULAR_METRICS = ("specular_precision", "specular_recall", "specular_added", "specular_colour_deg",
                    "specular_nyquist")


def plot_speed_accuracy(summary: list[dict[str, Any]], path: Path) -> None:
    """Time (log) against masked sRGB PSNR and FLIP: the path-tracing ladder as a curve, others as points."""
    import matplotlib  # here, not at the top: it takes ~0.5 s to import, and only plots need it

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


def write_compare_report(config: Any, summary: list[dict[str, Any]], sheets: list[str], out: Path,
                         metrics: Sequence[str] = COMPARE_METRICS) -> None:
    """``report.html`` of ``ngp-mi compare``: conventions, the results table, the plot and the sheets."""
    b = backend.load()
    keys = ["median_ms", "path_ms_at_equal_flip", "speedup"] + [f"{m}{suffix}" for suffix in ("", "_masked")
                                                              for m in metrics]
    keys += [k for k in ("fid", "kid", *SPECULAR_METRICS) if any(k in s for s in summary)]
    names = {"median_ms": "median ms", "path_ms_at_equal_flip": "path tracing ms at equal FLIP",
             "speedup": "× faster than path tracing"}
    head = ["method"] + [names.get(k, k) for k in keys]
    def cell(entry: dict[str, Any], key: str) -> str:
        text = fmt(entry.get(key, ""))
        note = entry.get("equal_flip_note", "interpolated")
        if key == "path_ms_at_equal_flip" and text and note != "interpolated":
            text = ("≤ " if note.startswith("at most") else "> ") + text
        return text

    rows = "\n".join(f"<tr><td>{html.escape(s['method'])}</td>" + "".join(f"<td>{cell(s, k)}</td>" for k in keys)
                     + "</tr>" for s in summary)
    ref = next(s for s in summary if s["kind"] == "reference")
    if "fid" in keys:
        fid_note = (f"FID / KID: Inception-v3 pool3 features ({html.escape(str(config.inception_weights))}) of each "
                    "method's sRGB images against the reference images of the same views; KID is the unbiased "
                    "cubic-kernel MMD². With few images FID is strongly biased upwards (its covariances have "
                    "rank &lt; images): compare methods within this table only.")
    else:
        fid_note = "FID / KID not computed: " + html.escape(missing_weights_message(None)) + "."
    images = "\n".join(f'<p>{html.escape(name)}</p><img src="images/{html.escape(name)}">' for name in sheets)
    text = f"""<!doctype html><html><head><meta charset="utf-8"><title>ngp-mi compare</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:auto}} table{{border-collapse:collapse;font-size:12px}}
td,th{{border:1px solid #ccc;padding:3px 6px;text-align:right}} td:first-child{{text-align:left}}</style></head><body>
<h1>Deferred shading vs path tracing</h1>
<p>{config.num_shapes} shapes of <code>{html.escape(config.source)}</code> × {config.views} views × lights
{', '.join(config.light_setups)} at {config.resolution}²; {b.variant}, {b.threads} threads, Mitsuba {b.mi.__version__}.
Reference: path tracing (max depth 6) at {config.reference_spp} spp ({fmt(ref['median_ms'])} ms per image).</p>
<h2>Conventions</h2>
<ul><li>All images are linear RGB radiance. R_diff and R_BP are divided by π: R_diff with k_d = 1 equals the
radiance of a Lambertian surface of albedo I_d under the same lights, and R_BP uses the paper's constants
(k_d {config.constants.k_d}, k_s {config.constants.k_s}, α {config.constants.alpha:g}); NGP's R_diff shades with
k_d {config.constants.diffuse_k_d:g} (the model's k_diff, else R_BP's k_d).</li>
<li>No exposure or tone mapping; sRGB metrics apply the sRGB transfer function to values clipped to [0, 1].</li>
<li>PSNR uses peak 1; SSIM is scikit-image's (Gaussian σ 1.5); FLIP is NVIDIA's (LDR, 67 pixels per degree).
"_masked" averages over the object only (mask of the G-buffer); times are medians over images, after a warm-up.
"Path tracing ms at equal FLIP": the spp ladder's time interpolated (log-log) at the method's FLIP; "≤" when the
lowest rung is already as good, "&gt;" when the highest rung is still worse.</li>
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
<li>specular_*: where G_sp^real puts its light. With A the light NGP adds to the image w/o G_sp^real and E the
light the reference has beyond that image (both clipped at 0, linear, on the object): precision = Σ min(A, E) / Σ A
(the share of the added light the reference also has), recall = Σ min(A, E) / Σ E, added = mean A; nyquist =
the share of the layer's AC power (NGP − w/o G_sp^real, whole image) at the Nyquist frequencies, a 2-pixel checkerboard (white noise:
3 / pixels). The last column of each sheet shows A (top) and E (bottom), ×4.</li>
<li>{fid_note}</li></ul>
<h2>Results</h2><table><tr>{''.join(f'<th>{html.escape(h)}</th>' for h in head)}</tr>
{rows}</table>
<h2>Speed against accuracy</h2><img src="speed_accuracy.png" width="1100">
<h2>Images (top: renders; bottom: FLIP error against the reference)</h2>{images}
</body></html>"""
    write_text(out / "report.html", text)


def fmt(value: Any) -> str:
    """A table cell: 3 decimals below 10, 1 above, 2 significant digits below 0.01 (shares such as
    ``specular_nyquist`` live there and 3 decimals would print them as 0), ∞ for infinity."""
    if isinstance(value, float):
        if math.isinf(value):
            return "∞"
        if 0 < abs(value) < 0.01:
            return f"{value:.2g}"
        return f"{value:.3f}" if abs(value) < 10 else f"{value:.1f}"
    return str(value)
