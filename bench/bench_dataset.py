"""Benchmark: dataset throughput (views/s including EXR writing), ngp-mi vs Blender Cycles, and RSS.

Same meshes (procedural chairs), same cameras, same passes (z-depth, normal, diffuse albedo,
position / NOC, mask / alpha), one sample per pixel, the same lossless EXR codec on both sides,
2 cores each:

* ngp-mi: ``render_dataset`` end to end, as ``ngp-mi render-dataset`` runs it (one worker process
  per core, including their start-up; scene building, rendering, EXR writing, manifest) over
  ``--shapes`` x ``--views`` views.
* Blender: ``bench/blender_gbuffer.py`` in ``.venv-blender`` (PyPI ``bpy`` 5.0.1 needs numpy < 2, so
  it gets its own virtualenv, created here on first use), Cycles on 2 threads: per-view time of
  ``render`` with ``write_still`` (multi-layer EXR) over the first ``--blender-shapes`` shapes,
  excluding start-up and mesh creation. It runs before and after ngp-mi; the faster run counts.
* Rendering alone (no files): ngp-mi's ``render_views`` vs Cycles without ``write_still``.
* RSS of one process over ``--rss-views`` views at 64² (8 chunks).

    .venv/bin/python bench/bench_dataset.py [--shapes 300] [--views 10] [--codecs rle,zip,none] [--skip-blender]
"""

from __future__ import annotations

import argparse
import dataclasses
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
from ngp_mi.data.render_dataset import DatasetConfig, default_workers, render_dataset
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


def blender_views_per_second(config: DatasetConfig, shapes: int, work: Path, write: bool = True) -> tuple[float, float, str]:
    """(views/s, median ms per view) of Cycles on the first ``shapes`` shapes' meshes and cameras."""
    python = blender_python()
    if python is None:
        return float("nan"), float("nan"), "unavailable"
    work.mkdir(parents=True, exist_ok=True)
    jobs = []
    for index in range(shapes):
        obj = generate(config.source, config.seed + index)
        mesh = obj.mesh()
        albedo = np.array([obj.materials[k].albedo if k in obj.materials else (0.5, 0.5, 0.5)
                           for k in range(int(mesh.part_ids.max()) + 1)])
        npz = work / f"shape{index}.npz"
        np.savez(npz, vertices=mesh.vertices, faces=mesh.faces, part_ids=mesh.part_ids, albedo=albedo)
        matrices = []
        for camera in config.cameras(index):
            M = np.eye(4)
            M[:3, :3] = camera.R.T @ np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes -> Blender's (-Z forward)
            M[:3, 3] = camera.position
            matrices.append(M.ravel().tolist())
        jobs.append({"npz": str(npz), "cameras": matrices})
    job = work / "job.json"
    job.write_text(json.dumps({"resolution": config.resolution, "threads": 2, "out": str(work / "blender"),
                               "write": write, "codec": config.compression.upper(), "shapes": jobs}))
    done = subprocess.run([str(python), str(ROOT / "bench" / "blender_gbuffer.py"), str(job)],
                          capture_output=True, text=True, check=True)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    times = result["times"][1:]  # the first view includes kernel loading
    return len(times) / sum(times), 1e3 * statistics.median(times), result["blender"]


def render_ms(config: DatasetConfig, shapes: int) -> float:
    """Median ms per view of ngp-mi's G-buffer rendering alone (``render_views``, no files)."""
    from ngp_mi.data.sources import resolve_source
    from ngp_mi.render.gbuffer import GBufferRenderer

    times = []
    for index, item in enumerate(resolve_source(config.source, shapes, config.seed)):
        content = item.load()
        cameras = config.cameras(index)
        renderer = GBufferRenderer(content.shapes, content.bounds, cameras[0], config.channels)
        for repeat in range(3):
            start = time.perf_counter()
            renderer.render_views(cameras)
            times.append((time.perf_counter() - start) / len(cameras))
    return 1e3 * statistics.median(times)


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2 ** 20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--shapes", type=int, default=300)
    parser.add_argument("--views", type=int, default=10)
    parser.add_argument("--blender-shapes", type=int, default=30)
    parser.add_argument("--codecs", default="rle,zip,none")
    parser.add_argument("--resolutions", default="128,256")
    parser.add_argument("--rss-views", type=int, default=2000)
    parser.add_argument("--skip-blender", action="store_true")
    args = parser.parse_args()
    b = backend.load()
    workers = default_workers()
    work = Path(tempfile.mkdtemp(prefix="bench_dataset_"))
    rows, render_rows = [], []
    try:
        # Warm the kernel cache so that neither side pays compilation in its timed views.
        render_dataset(DatasetConfig(source="chair", num_shapes=2, views=2, resolution=128), work / "warm", progress=False)
        for res in (int(r) for r in args.resolutions.split(",")):
            base = DatasetConfig(source="chair", num_shapes=args.shapes, views=args.views, resolution=res)
            render_dataset(dataclasses.replace(base, num_shapes=2), work / f"warm{res}", progress=False)
            for codec in args.codecs.split(","):
                config = dataclasses.replace(base, compression=codec)
                theirs = []

                def cycles(attempt: str) -> None:
                    if not args.skip_blender:
                        theirs.append(blender_views_per_second(config, args.blender_shapes,
                                                               work / f"blender{res}{codec}{attempt}"))

                # Outputs stay until the end: deleting thousands of files makes ext4 scan its recently
                # deleted inodes on every file created in the next seconds (up to 2x the system time).
                cycles("before")
                ours = render_dataset(config, work / f"ours{res}{codec}", progress=False, workers=workers)
                cycles("after")
                best = max(theirs, key=lambda t: t[0]) if theirs else (float("nan"), float("nan"), "skipped")
                rows.append((res, codec, ours["views_per_second"], ours["views_rendered"], *best))
            if not args.skip_blender:
                cycles_ms = blender_views_per_second(base, args.blender_shapes, work / f"blender{res}", write=False)[1]
            else:
                cycles_ms = float("nan")
            render_rows.append((res, render_ms(base, args.blender_shapes), cycles_ms))

        start_rss = rss_mib()
        per_chunk = max(10, args.rss_views // 8)
        rss = []
        for chunk in range(8):
            config = DatasetConfig(source="chair", num_shapes=per_chunk // 10, views=10, resolution=64, seed=1000 * chunk)
            render_dataset(config, work / f"rss{chunk}", progress=False)
            rss.append(rss_mib())
    finally:
        shutil.rmtree(work, ignore_errors=True)

    print(f"# bench_dataset — {time.strftime('%Y-%m-%d')}, {platform.machine()}, {b.variant}; ngp-mi: {workers} worker "
          f"processes; Blender: 2 threads; channels depth, normal, albedo, noc, mask\n")
    print("| res | codec | ngp-mi views/s (views) | Blender Cycles views/s (median ms) | ratio |\n|---|---|---|---|---|")
    for res, codec, ours, count, theirs, theirs_ms, version in rows:
        print(f"| {res}² | {codec} | {ours:.1f} ({count}) | {theirs:.1f} ({theirs_ms:.1f} ms, {version}) | "
              f"{ours / theirs:.1f}x |")
    print("\nRendering alone (no files), median ms per view:\n\n| res | ngp-mi render_views | Blender Cycles | ratio |\n"
          "|---|---|---|---|")
    for res, ours_ms, cycles_ms in render_rows:
        print(f"| {res}² | {ours_ms:.2f} | {cycles_ms:.2f} | {cycles_ms / ours_ms:.1f}x |")
    print(f"\nRSS over {8 * per_chunk} views at 64² (one process, 8 chunks): start {start_rss:.1f} MiB, after each chunk "
          + ", ".join(f"{r:.1f}" for r in rss) + f" MiB; growth {rss[-1] - rss[0]:+.1f} MiB after the first chunk")


if __name__ == "__main__":
    main()
