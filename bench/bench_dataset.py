"""Benchmark: dataset throughput (views/s including EXR writing), ngp-mi vs Blender Cycles, and RSS.

Same meshes (procedural chairs 0..N-1), same cameras, same passes (z-depth, normal, diffuse
albedo, position / NOC, mask / alpha), one sample per pixel, ZIP-compressed float EXR, 2 threads:

* ngp-mi: ``render_dataset`` end to end (scene building, rendering, EXR writing, manifest).
* Blender: ``bench/blender_gbuffer.py`` in ``.venv-blender`` (PyPI ``bpy`` 5.0.1 needs numpy < 2, so
  it gets its own virtualenv, created here on first use): per-view time of ``render`` with
  ``write_still`` (multi-part EXR), excluding start-up and mesh creation.
* RSS of one process over ``--rss-views`` views (200 shapes x 10 views at 64²).

    .venv/bin/python bench/bench_dataset.py [--shapes 10] [--views 10] [--skip-blender]
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ngp_mi import backend
from ngp_mi.data.render_dataset import DatasetConfig, render_dataset, view_cameras
from ngp_mi.geometry.families import generate

ROOT = Path(__file__).resolve().parent.parent
BLENDER_VENV = ROOT / ".venv-blender"


def blender_python() -> Path | None:
    python = BLENDER_VENV / "bin" / "python"
    if not python.exists():
        print("creating .venv-blender with bpy==5.0.1 (about 400 MB, once) ...", file=sys.stderr)
        try:
            subprocess.run([sys.executable, "-m", "venv", str(BLENDER_VENV)], check=True)
            subprocess.run([str(python), "-m", "pip", "install", "--quiet", "bpy==5.0.1", "numpy<2"], check=True)
        except subprocess.CalledProcessError as exc:
            print(f"cannot install bpy ({exc}); skipping Blender", file=sys.stderr)
            return None
    return python


def blender_views_per_second(config: DatasetConfig, work: Path, write: bool = True) -> tuple[float, float, str]:
    """(views/s, median ms per view) of Cycles on the same meshes and cameras (with or without EXR writing)."""
    python = blender_python()
    if python is None:
        return float("nan"), float("nan"), "unavailable"
    shapes = []
    for index in range(config.num_shapes):
        obj = generate(config.source, config.seed + index)
        mesh = obj.mesh()
        albedo = np.array([obj.materials[k].albedo if k in obj.materials else (0.5, 0.5, 0.5)
                           for k in range(int(mesh.part_ids.max()) + 1)])
        npz = work / f"shape{index}.npz"
        np.savez(npz, vertices=mesh.vertices, faces=mesh.faces, part_ids=mesh.part_ids, albedo=albedo)
        matrices = []
        for camera in view_cameras(config, index):
            M = np.eye(4)
            M[:3, :3] = camera.R.T @ np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes -> Blender's (-Z forward)
            M[:3, 3] = camera.position
            matrices.append(M.ravel().tolist())
        shapes.append({"npz": str(npz), "cameras": matrices})
    job = work / "job.json"
    job.write_text(json.dumps({"resolution": config.resolution, "threads": 2, "out": str(work / "blender"),
                               "write": write, "shapes": shapes}))
    done = subprocess.run([str(python), str(ROOT / "bench" / "blender_gbuffer.py"), str(job)],
                          capture_output=True, text=True, check=True)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    times = result["times"][1:]  # the first view includes kernel loading
    return len(times) / sum(times), 1e3 * statistics.median(times), result["blender"]


def gbuffer_ms(config: DatasetConfig) -> float:
    """Median ms of ngp-mi's G-buffer render alone (no EXR), over the benchmark's views."""
    from ngp_mi.data.sources import resolve_source
    from ngp_mi.render.gbuffer import GBufferRenderer

    times = []
    for index, item in enumerate(resolve_source(config.source, config.num_shapes, config.seed)):
        content = item.load()
        cameras = view_cameras(config, index)
        renderer = GBufferRenderer(content.shapes, content.bounds, cameras[0], config.channels)
        for camera in cameras:
            start = time.perf_counter()
            renderer.render(camera)
            times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2 ** 20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--shapes", type=int, default=10)
    parser.add_argument("--views", type=int, default=10)
    parser.add_argument("--rss-views", type=int, default=2000)
    parser.add_argument("--skip-blender", action="store_true")
    args = parser.parse_args()
    b = backend.load()
    work = Path(tempfile.mkdtemp(prefix="bench_dataset_"))
    rows = []
    try:
        # Warm the kernel cache so that neither side pays compilation in its timed views.
        render_dataset(DatasetConfig(source="chair", num_shapes=1, views=2, resolution=128), work / "warm", progress=False)
        for res in (128, 256):
            config = DatasetConfig(source="chair", num_shapes=args.shapes, views=args.views, resolution=res)
            ours = render_dataset(config, work / f"ours{res}", progress=False)["views_per_second"]
            half = render_dataset(dataclass_replace(config, half=True), work / f"half{res}", progress=False)["views_per_second"]
            ours_render_ms = gbuffer_ms(config)
            if args.skip_blender:
                theirs, theirs_ms, version, render_only_ms = float("nan"), float("nan"), "skipped", float("nan")
            else:
                (work / f"blender{res}").mkdir()
                theirs, theirs_ms, version = blender_views_per_second(config, work / f"blender{res}")
                render_only_ms = blender_views_per_second(config, work / f"blender{res}", write=False)[1]
            rows.append((res, ours, half, theirs, theirs_ms, version, ours_render_ms, render_only_ms))

        start_rss = rss_mib()
        per_chunk = max(1, args.rss_views // 8)
        rss = []
        for chunk in range(8):
            config = DatasetConfig(source="chair", num_shapes=per_chunk // 10, views=10, resolution=64, seed=1000 * chunk)
            render_dataset(config, work / f"rss{chunk}", progress=False)
            rss.append(rss_mib())
    finally:
        shutil.rmtree(work, ignore_errors=True)

    print(f"# bench_dataset — {time.strftime('%Y-%m-%d')}, {platform.machine()}, {b.variant}, {b.threads} threads; "
          f"{args.shapes} procedural chairs x {args.views} views; channels depth, normal, albedo, noc, mask\n")
    print("| res | ngp-mi views/s | ngp-mi --half views/s | Blender Cycles views/s (median ms) | ratio | ratio --half |\n"
          "|---|---|---|---|---|---|")
    for res, ours, half, theirs, theirs_ms, version, *_ in rows:
        print(f"| {res}² | {ours:.1f} | {half:.1f} | {theirs:.1f} ({theirs_ms:.1f} ms, {version}) | "
              f"{ours / theirs:.1f}x | {half / theirs:.1f}x |")
    print("\nRendering alone (no EXR), median ms per view:\n\n| res | ngp-mi G-buffer | Blender Cycles | ratio |\n"
          "|---|---|---|---|")
    for res, *_, ours_render_ms, render_only_ms in rows:
        print(f"| {res}² | {ours_render_ms:.2f} | {render_only_ms:.2f} | {render_only_ms / ours_render_ms:.1f}x |")
    print(f"\nRSS over {8 * per_chunk} views at 64² (one process, 8 chunks): start {start_rss:.1f} MiB, after each chunk "
          + ", ".join(f"{r:.1f}" for r in rss) + f" MiB; growth {rss[-1] - rss[0]:+.1f} MiB after the first chunk")


def dataclass_replace(config: DatasetConfig, **changes) -> DatasetConfig:
    import dataclasses

    return dataclasses.replace(config, **changes)


if __name__ == "__main__":
    main()
