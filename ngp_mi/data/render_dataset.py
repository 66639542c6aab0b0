"""``ngp-mi render-dataset``: reference maps (and "real" path-traced images) for many shapes and views.

Layout of ``OUT``::

    dataset.json                     the settings (a resumed run must use the same ones)
    maps/<shape id>/<view>.exr       the requested G-buffer channels (``render.gbuffer``)
    real/<shape id>/<view>.exr|.png  path-traced image, linear EXR + sRGB PNG (``--real-spp`` > 0)
    manifest[.shard-K-of-N].jsonl    one record per finished view
    summary[.shard-K-of-N].json      counts, rate and the reasons of skipped shapes
    render-dataset.log               the log

A view is finished once its manifest line is written, which happens after its files were
written atomically: a killed run leaves no partial file and a re-run renders only what is
missing. ``--shard K/N`` takes every N-th shape starting at K, so N processes (or machines) can
share the work; each writes its own manifest, and :func:`load_manifest` reads them all.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import platform
import queue
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from ngp_mi import __version__, backend
from ngp_mi.camera import Camera, ViewDistribution
from ngp_mi.data.exr import write_exr
from ngp_mi.data.sources import SourceItem, autoencoded_items, resolve_source
from ngp_mi.lights import DirectionalLight, Light, overhead_rig
from ngp_mi.render.gbuffer import CHANNELS, GBufferRenderer
from ngp_mi.render.scene import build_scene, lights_to_mitsuba, render, set_sensor_camera
from ngp_mi.viz import save_png, to_uint8

log = logging.getLogger("ngp_mi.render_dataset")
LIGHT_MODES = ("rig", "random", "scene")


@dataclasses.dataclass(frozen=True)
class DatasetConfig:
    source: str
    num_shapes: int = 16
    views: int = 8
    resolution: int = 128
    channels: tuple[str, ...] = CHANNELS
    real_spp: int = 0
    lights: str = "rig"
    seed: int = 0
    compression: str = "zip"
    half: bool = False  # store every channel but depth as 16-bit float
    coarse_shapes: str | None = None  # a `train shape` run: render the shapes as its autoencoder reconstructs them
    coarse_resolution: int = 64       # marching-cubes grid of those reconstructions
    view_distribution: ViewDistribution = ViewDistribution()

    def __post_init__(self) -> None:
        unknown = [c for c in self.channels if c not in CHANNELS]
        if unknown or not self.channels:
            raise ValueError(f"--channels must be a non-empty subset of {','.join(CHANNELS)}; got {','.join(self.channels)}")
        if self.lights not in LIGHT_MODES:
            raise ValueError(f"--lights must be one of {LIGHT_MODES}, got {self.lights!r}")
        for name in ("num_shapes", "views", "resolution"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        if self.real_spp < 0:
            raise ValueError(f"--real-spp must be >= 0, got {self.real_spp}")

    def to_json(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        data["channels"] = list(self.channels)
        return data


def parse_shard(text: str) -> tuple[int, int]:
    """``"k/n"`` → (k, n) with 0 <= k < n."""
    try:
        k, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise ValueError(f"--shard must look like K/N (e.g. 0/4), got {text!r}") from None
    if not 0 <= k < n:
        raise ValueError(f"--shard K/N needs 0 <= K < N, got {text!r}")
    return k, n


def _shard_suffix(shard: tuple[int, int]) -> str:
    return "" if shard == (0, 1) else f".shard-{shard[0]}-of-{shard[1]}"


def derived_seed(*keys: int) -> int:
    """A 32-bit seed from integer keys (``numpy.random.SeedSequence``): stable across runs and shards."""
    return int(np.random.SeedSequence([int(k) for k in keys]).generate_state(1)[0])


def view_cameras(config: DatasetConfig, shape_index: int) -> list[Camera]:
    """The views of shape ``shape_index``: seeded by (seed, shape index), independent of sharding."""
    return config.view_distribution.sample(config.views, seed=derived_seed(config.seed, shape_index),
                                           resolution=config.resolution)


def view_lights(config: DatasetConfig, shape_index: int, view: int) -> list[Light]:
    """Lights of one view: the overhead rig, or 1–4 random white-ish directional lights."""
    if config.lights != "random":
        return overhead_rig()
    rng = np.random.default_rng([config.seed, shape_index, view, 7])
    lights = []
    for _ in range(int(rng.integers(1, 5))):
        el, az = np.radians(rng.uniform(15, 85)), rng.uniform(0, 2 * np.pi)
        colour = rng.uniform(0.8, 1.0, 3) * rng.uniform(0.3, 1.5)
        lights.append(DirectionalLight((np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)), tuple(colour)))
    return lights


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    """Records of a JSON-lines file; a torn last line (a killed writer) is ignored."""
    records = []
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                log.warning("%s: ignoring a torn line", path)
    return records


def load_manifest(root: str | Path) -> list[dict[str, Any]]:
    """All view records of a dataset folder (every shard's manifest), sorted by (shape, view)."""
    root = Path(root)
    records = {}
    for path in sorted(root.glob("manifest*.jsonl")):
        for record in read_jsonl(path):
            records[(record["shape_id"], record["view"])] = record
    if not records:
        raise ValueError(f"{root}: no manifest*.jsonl with records; render the dataset first")
    return [records[k] for k in sorted(records)]


class _ManifestWriter:
    """Appends records, one line each; drops a torn last line left by a killed run first.

    Each line is flushed to the OS, which survives the process being killed (the failure a long
    job must tolerate); it is not fsync'ed per view (1 ms each), so a power loss may lose the last
    records, whose views are then simply rendered again.
    """

    def __init__(self, path: Path):
        self.path = path
        if path.exists():
            text = path.read_bytes()
            if text and not text.endswith(b"\n"):
                path.write_bytes(text[: text.rfind(b"\n") + 1])
        self.file = open(path, "a")

    def append(self, record: dict[str, Any]) -> None:
        self.file.write(json.dumps(record) + "\n")
        self.file.flush()

    def close(self) -> None:
        self.file.flush()
        os.fsync(self.file.fileno())
        self.file.close()


class _BackgroundWriter:
    """Writes each view's files and then its manifest line on ``threads`` threads.

    EXR compression releases the GIL for part of its work, so writes overlap each other and the
    next view's rendering. A view's line follows its own files; lines of different views may come
    in any order (readers sort). A failed write (disk full, permissions) stops the job at the
    next submit.
    """

    def __init__(self, manifest: _ManifestWriter, threads: int = 2, depth: int = 8):
        self.manifest = manifest
        self.jobs: queue.Queue = queue.Queue(maxsize=depth)
        self.error: BaseException | None = None
        self.lock = threading.Lock()
        self.threads = [threading.Thread(target=self._run, name=f"render-dataset-writer-{i}", daemon=True)
                        for i in range(threads)]
        for thread in self.threads:
            thread.start()

    def submit(self, write: Callable[[], None], record: dict[str, Any], done: Callable[[], None]) -> None:
        if self.error is not None:
            raise self.error
        self.jobs.put((write, record, done))

    def _run(self) -> None:
        while (job := self.jobs.get()) is not None:
            write, record, done = job
            if self.error is None:
                try:
                    write()
                    with self.lock:
                        self.manifest.append(record)
                        done()
                except BaseException as exc:  # reported to the main thread
                    self.error = exc

    def close(self) -> None:
        for _ in self.threads:
            self.jobs.put(None)
        for thread in self.threads:
            thread.join()
        self.manifest.close()
        if self.error is not None:
            raise self.error


def _check_settings(out: Path, config: DatasetConfig) -> None:
    settings = out / "dataset.json"
    current = config.to_json()
    if settings.exists():
        previous = json.loads(settings.read_text())
        # a setting added after the folder was rendered counts as its default
        defaults = json.loads(json.dumps(DatasetConfig(source=config.source).to_json()))
        changed = {k for k in current if previous.get(k, defaults[k]) != json.loads(json.dumps(current[k]))}
        if changed:
            raise ValueError(f"{settings}: this folder was rendered with other settings ({', '.join(sorted(changed))}); "
                             "use a new --out or the same settings to resume")
    else:
        tmp = settings.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(current, indent=1) + "\n")
        os.replace(tmp, settings)


def render_dataset(config: DatasetConfig, out: str | Path, shard: tuple[int, int] = (0, 1),
                   strict: bool = False, progress: bool = True) -> dict[str, Any]:
    """Render (or finish rendering) this shard of the dataset; returns the summary."""
    from tqdm import tqdm

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(out / "render-dataset.log")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    try:
        _check_settings(out, config)
        if config.coarse_shapes:
            items = autoencoded_items(config.source, config.num_shapes, config.seed, config.coarse_shapes,
                                      config.coarse_resolution)
        else:
            items = resolve_source(config.source, config.num_shapes, config.seed)
        mine = [(i, item) for i, item in enumerate(items) if i % shard[1] == shard[0]]
        suffix = _shard_suffix(shard)
        manifest_path = out / f"manifest{suffix}.jsonl"
        done = {(r["shape_id"], r["view"]) for r in read_jsonl(manifest_path)}
        total = len(mine) * config.views
        summary: dict[str, Any] = {"shard": list(shard), "views_total": total, "views_before": len(done),
                                   "views_rendered": 0, "skipped_shapes": {}}
        versions = {"ngp_mi": __version__, **backend.versions(), "python": platform.python_version()}
        writer = _BackgroundWriter(_ManifestWriter(manifest_path))
        start = time.perf_counter()
        bar = tqdm(total=total, initial=len(done), unit="view", disable=not progress, dynamic_ncols=True,
                   desc=f"render-dataset{suffix or ''}")
        try:
            for index, item in mine:
                todo = [v for v in range(config.views) if (item.id, v) not in done]
                if not todo:
                    continue
                try:
                    rendered = _render_shape(config, out, index, item, todo, writer, versions, bar)
                except Exception as exc:  # a bad shape is skipped with its reason, the job goes on
                    reason = f"{type(exc).__name__}: {exc}"
                    log.warning("skipping %s (%s): %s", item.id, item.origin, reason)
                    summary["skipped_shapes"][item.id] = reason
                    bar.update(len(todo))
                    continue
                summary["views_rendered"] += rendered
        finally:
            try:
                writer.close()
            finally:
                bar.close()
        elapsed = time.perf_counter() - start
        summary["seconds"] = round(elapsed, 3)
        summary["views_per_second"] = round(summary["views_rendered"] / elapsed, 3) if elapsed > 0 else None
        summary_path = out / f"summary{suffix}.json"
        summary_path.write_text(json.dumps(summary, indent=1) + "\n")
        log.info("done: %d views rendered, %d already present, %d shapes skipped (%s)", summary["views_rendered"],
                 summary["views_before"], len(summary["skipped_shapes"]), summary_path)
        if strict and summary["skipped_shapes"]:
            raise RuntimeError(f"--strict: {len(summary['skipped_shapes'])} shape(s) skipped, see {summary_path}")
        return summary
    finally:
        log.removeHandler(handler)
        handler.close()


def _render_shape(config: DatasetConfig, out: Path, index: int, item: SourceItem, views: Iterable[int],
                  writer: _BackgroundWriter, versions: dict[str, str], bar: Any) -> int:
    content = item.load()
    cameras = view_cameras(config, index)
    gbuffer = GBufferRenderer(content.shapes, content.bounds, cameras[0], config.channels)
    real_scene = None
    if config.real_spp and config.lights == "scene" and not content.emitters:
        raise ValueError("--lights scene needs emitters in the scene file")
    count = 0
    for view in views:
        camera = cameras[view]
        lights = view_lights(config, index, view) if config.lights != "scene" else []
        stem = f"{item.id}/{view:03d}"
        maps = gbuffer.render(camera)
        files = {"maps": f"maps/{stem}.exr"}
        image = None
        if config.real_spp:
            if real_scene is None or config.lights == "random":
                emitters = content.emitters if config.lights == "scene" else lights_to_mitsuba(lights)
                real_scene = build_scene(camera, {**content.shapes, **emitters}, (), {"type": "path", "max_depth": 6},
                                         spp=config.real_spp)
            set_sensor_camera(real_scene.sensors()[0], camera)
            image = render(real_scene, seed=derived_seed(config.seed, index, view))[..., :3]
            files["real"] = f"real/{stem}.exr"
            files["real_png"] = f"real/{stem}.png"

        def write(maps=maps, image=image, files=files, view=view) -> None:
            write_exr(out / files["maps"], maps, config.compression,
                      metadata={"ngp_mi.shape_id": item.id, "ngp_mi.view": str(view)},
                      half=[c for c in maps if c != "depth"] if config.half else ())
            if image is not None:
                write_exr(out / files["real"], {"rgb": image}, config.compression)
                save_png(out / files["real_png"], to_uint8(image))

        writer.submit(write, {
            "shape_id": item.id, "source": item.kind, "origin": item.origin, "shape_index": index, "view": view,
            "theta_deg": camera.theta_deg, "phi_deg": camera.phi_deg, "K": camera.K.tolist(), "E": camera.E.tolist(),
            "width": camera.width, "height": camera.height, "channels": list(config.channels),
            "lights": [l.to_dict() for l in lights] if config.lights != "scene" else "scene",
            "seed": config.seed, "real_spp": config.real_spp, "files": files, "bounds": content.bounds.tolist(),
            "shape": content.meta, "versions": versions,
        }, lambda: bar.update(1))
        count += 1
    return count
