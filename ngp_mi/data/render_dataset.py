"""``ngp-mi render-dataset``: reference maps (and "real" path-traced images) for many shapes and views.

Layout of ``OUT``::

    dataset.json                     the settings (a resumed run must use the same ones)
    maps/<shape id>/<view>.exr       the requested G-buffer channels (``render.gbuffer``)
    real/<shape id>/<view>.exr|.png  path-traced image, linear EXR (``rgb`` and ``alpha``, the pixel's
                                     box-filtered coverage) + sRGB PNG (``--real-spp`` > 0)
    manifest[.shard-K-of-N].jsonl    one record per finished view
    summary[.shard-K-of-N].json      counts, rate and the reasons of skipped shapes
    render-dataset.log               the log
    render-dataset[.shard-K-of-N].lock         who renders this shard now (:mod:`ngp_mi.lock`)
    render-dataset[.shard-K-of-N].workers.lock held by that job's worker processes

A view is finished once its manifest line is written, which happens after its files were
written atomically: a killed run leaves no partial file and a re-run renders only what is
missing (whatever shard or worker rendered the rest). ``--shard K/N`` takes every N-th shape
starting at K, so N processes (or machines) can share the work; each writes its own manifest,
and :func:`load_manifest` reads them all. One job at a time renders a shard: a second one into the
same folder and shard is refused with the first one's pid, host and command.

Before anything is written the source is resolved (a missing file or an empty folder is one clear
error) and the memory the job needs is estimated (:meth:`DatasetConfig.memory_needed`): a job that
cannot fit is refused with the figure. A shape that fails to load, or that no view sees, is
skipped with its reason; a job that renders nothing while views are missing exits with an error.

Speed (``bench/RESULTS.md``): all views of a shape are rendered by one kernel
(:meth:`GBufferRenderer.render_views`); maps are stored in the object's bounding rectangle (the
EXR data window; ``full_window`` stores every pixel) with RLE compression by default; and
``workers`` processes split a shard like ``--shard`` does, each with Dr.Jit on one thread and
its own writer threads. Processes rather than threads: in one process Dr.Jit's worker threads spin
for a while after every kernel and the EXR writers share the GIL; at 128² one process rendered 166
views/s with Dr.Jit on 2 threads and 410 on 1 thread, two processes 600–800 (2 cores).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import logging
import os
import platform
import socket
import time
from pathlib import Path
from typing import Any, Iterator, Sequence

from tqdm import tqdm

from ngp_mi import __version__, backend, lock
from ngp_mi.atomic import write_json
from ngp_mi.camera import Camera, ViewDistribution
from ngp_mi.data.exr import COMPRESSIONS, nonzero_windows, write_exr
from ngp_mi.data.manifest import BackgroundWriter, ManifestWriter, load_manifest, manifest_records
from ngp_mi.data.sources import Reconstruct, SourceItem, autoencoded_items, coarse_shapes_of, source_items
from ngp_mi.data.views import LIGHT_MODES, derived_seed, view_cameras, view_lights
from ngp_mi.data.workers import BarProgress, run_workers
from ngp_mi.geometry.sources import ShapeRef, resolve_shapes
from ngp_mi.lights import Light
from ngp_mi.render.gbuffer import CHANNELS, LANES_PER_LAUNCH, GBufferRenderer
from ngp_mi.render.scene import build_scene, lights_to_mitsuba, render, set_sensor_camera
from ngp_mi.viz import save_png, to_uint8

log = logging.getLogger("ngp_mi.render_dataset")
STORAGE_SETTINGS = ("compression", "full_window")  # how maps are stored, not what they hold: may change on resume
CHANNEL_WIDTH = {"depth": 1, "mask": 1, "normal": 3, "albedo": 3, "noc": 3}
MAX_LANES = (1 << 32) - 1  # Dr.Jit's arrays (one lane per pixel of a launch) hold at most this many entries
# Measured peaks (bench/RESULTS.md, "Memory of a dataset job"), rounded up: per pixel of a launch, per stored
# float of a shape's maps (the launches' pieces and the stacked array), per pixel of a path-traced image (Mitsuba
# loops over its samples: the peak does not grow with --real-spp), and the process itself.
LAUNCH_BYTES_PER_LANE = 64
MAP_BYTES_PER_FLOAT = 8
PATH_BYTES_PER_PIXEL = 64
PROCESS_BYTES = 256 << 20
WORKERS_EXIT_SECONDS = 30.0  # how long a job waits for the workers of a killed one to notice (they take ~0.2 s)
__all__ = ["DatasetConfig", "default_workers", "load_manifest", "parse_shard", "render_dataset"]


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
    compression: str = "rle"
    full_window: bool = False  # store every pixel, not only the object's bounding rectangle
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
        if self.compression not in COMPRESSIONS:
            raise ValueError(f"--compression must be one of {sorted(COMPRESSIONS)}, got {self.compression!r}")

    def to_json(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        data["channels"] = list(self.channels)
        return data

    def cameras(self, shape_index: int) -> list[Camera]:
        """The views of shape ``shape_index``: seeded by (seed, shape index), independent of sharding."""
        return view_cameras(self.views, self.resolution, self.seed, shape_index, self.view_distribution)

    def memory_needed(self) -> int:
        """Bytes one process needs to render a shape: its launches, all its views' maps, a real image.

        Raises ValueError when one view has more pixels than a Dr.Jit launch can hold.
        """
        pixels = self.resolution ** 2
        if pixels > MAX_LANES:
            raise ValueError(f"--res {self.resolution}: one view is {pixels:,} pixels, more than the {MAX_LANES:,} "
                             f"a Dr.Jit launch holds (at most --res {int(MAX_LANES ** 0.5)})")
        floats = sum(CHANNEL_WIDTH[c] for c in {*self.channels, "mask"})
        launch = min(self.views * pixels, max(pixels, LANES_PER_LAUNCH)) * LAUNCH_BYTES_PER_LANE
        maps = self.views * pixels * floats * MAP_BYTES_PER_FLOAT
        real = pixels * PATH_BYTES_PER_PIXEL if self.real_spp else 0
        return PROCESS_BYTES + launch + maps + real

    def view_lights(self, shape_index: int, view: int) -> list[Light]:
        """The lights of one view's real image: the overhead rig or random lights (``scene``: none)."""
        return [] if self.lights == "scene" else view_lights(self.lights, self.seed, shape_index, view)


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


def _check_settings(out: Path, config: DatasetConfig) -> None:
    settings = out / "dataset.json"
    current = config.to_json()
    if settings.exists():
        previous = json.loads(settings.read_text())
        # a setting added after the folder was rendered counts as its default
        defaults = json.loads(json.dumps(DatasetConfig(source=config.source).to_json()))
        changed = {k for k in current if k not in STORAGE_SETTINGS
                   and previous.get(k, defaults[k]) != json.loads(json.dumps(current[k]))}
        if changed:
            raise ValueError(f"{settings}: this folder was rendered with other settings ({', '.join(sorted(changed))}); "
                             "use a new --out or the same settings to resume")
    else:  # a temporary name of its own: shards started together must not share one
        write_json(settings, current)


def available_memory() -> int:
    """Bytes the system can give without swapping (``MemAvailable``), or its physical memory."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_memory(config: DatasetConfig, workers: int, available: int | None = None) -> int:
    """Refuse (ValueError with the figures) a job whose processes would need more memory than is
    available; returns the estimate in bytes."""
    needed = workers * config.memory_needed()
    available = available_memory() if available is None else available
    if needed > available:
        gib = 1 << 30
        raise ValueError(f"this job needs about {needed / gib:.1f} GiB ({workers} process(es) x "
                         f"{config.views} views of {config.resolution}² with {', '.join(config.channels)}"
                         f"{f', --real-spp {config.real_spp}' if config.real_spp else ''}) but "
                         f"{available / gib:.1f} GiB are available on {socket.gethostname()}; "
                         "lower --res, --views, --real-spp or --workers")
    return needed


def default_workers() -> int:
    """One process per core (at most 8) on the CPU; one on a GPU, which a single process fills."""
    if backend.load().is_cuda:
        return 1
    return max(1, min(8, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1))


@contextlib.contextmanager
def _logging_to(out: Path) -> Iterator[None]:
    handler = logging.FileHandler(out / "render-dataset.log")  # append mode: workers share the file
    handler.setFormatter(logging.Formatter("%(asctime)s %(process)d %(levelname)s %(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    try:
        yield
    finally:
        log.removeHandler(handler)
        handler.close()


def render_dataset(config: DatasetConfig, out: str | Path, shard: tuple[int, int] = (0, 1),
                   strict: bool = False, progress: bool = True, workers: int = 1,
                   reconstruct: Reconstruct | None = None, wait: float = 0.0) -> dict[str, Any]:
    """Render (or finish rendering) this shard of the dataset; returns the summary.

    ``wait`` seconds: how long to wait for another job writing the shard (a training cache that
    jobs started together share) before :class:`ngp_mi.lock.Busy`; 0, the CLI's, fails at once.

    ``workers`` > 1 starts that many processes (:mod:`ngp_mi.data.workers`), worker j taking shard
    ``(K + N·j) / (N·workers)`` of the whole (so the shard is split like ``--shard`` splits the
    dataset); their progress, skipped shapes and failures come back to this process, which writes
    the shard's summary. ``config.coarse_shapes`` needs ``reconstruct``, the coarse version of a
    shape (:class:`ngp_mi.models.shape.CoarseShapes` of that run; this layer loads no model).
    """
    out = Path(out)
    if workers < 1:
        raise ValueError(f"--workers must be >= 1, got {workers}")
    if (config.coarse_shapes is None) != (reconstruct is None):
        raise ValueError("coarse_shapes and reconstruct go together: pass reconstruct=CoarseShapes(run, resolution) "
                         "(ngp_mi.models.shape) with a config's coarse_shapes, and neither without")
    # Checked once, here, before anything is written: workers get the resolved shapes.
    if reconstruct is not None:
        refs = coarse_shapes_of(config.source, config.num_shapes, config.seed)
    else:
        refs = resolve_shapes(config.source, config.num_shapes, config.seed)
    check_memory(config, workers)
    suffix = _shard_suffix(shard)
    with lock.exclusive(out / f"render-dataset{suffix}.lock", f"shard {shard[0]}/{shard[1]} of {out}", wait), \
            _logging_to(out):
        lock.wait_exclusive(_workers_lock(out, shard), "render-dataset", WORKERS_EXIT_SECONDS)
        _check_settings(out, config)
        bar = tqdm(total=0, unit="view", disable=not progress, dynamic_ncols=True, desc=f"render-dataset{suffix}")
        start = time.perf_counter()
        try:
            if workers == 1:
                summary = _render_part(config, out, shard, refs, reconstruct, BarProgress(bar))
            else:
                summary = _run_workers(config, out, shard, refs, reconstruct, workers, bar)
        finally:
            bar.close()
        elapsed = time.perf_counter() - start
        summary.update(shard=list(shard), workers=workers, seconds=round(elapsed, 3),
                       views_per_second=round(summary["views_rendered"] / elapsed, 3) if elapsed > 0 else None)
        summary_path = write_json(out / f"summary{suffix}.json", summary)
        log.info("done: %d views rendered, %d already present, %d shapes skipped (%s)", summary["views_rendered"],
                 summary["views_before"], len(summary["skipped_shapes"]), summary_path)
        if summary.get("failed_workers"):
            raise RuntimeError(f"{len(summary['failed_workers'])} worker(s) failed ({summary['failed_workers']}); "
                               f"what they finished is kept, re-run to render the rest (see {summary_path})")
        if strict and summary["skipped_shapes"]:
            raise RuntimeError(f"--strict: {len(summary['skipped_shapes'])} shape(s) skipped, see {summary_path}")
        if summary["views_rendered"] == 0 and summary["views_before"] < summary["views_total"]:
            raise RuntimeError(f"nothing was rendered: {len(summary['skipped_shapes'])} shape(s) skipped "
                               f"({'; '.join(f'{k}: {v}' for k, v in list(summary['skipped_shapes'].items())[:3])}), "
                               f"see {summary_path}")
        return summary


def _workers_lock(out: Path, shard: tuple[int, int]) -> Path:
    return out / f"render-dataset{_shard_suffix(shard)}.workers.lock"


def _worker(config: DatasetConfig, out: Path, shard: tuple[int, int], refs: Sequence[ShapeRef],
            reconstruct: Reconstruct | None, workers: int, worker: int, progress: Any) -> dict[str, Any]:
    """Worker ``worker`` of ``workers``: shard (K + N·worker) / (N·workers), Dr.Jit on one thread."""
    backend.load(threads=1)  # this process is one of the job's cores
    k, n = shard
    with lock.shared(_workers_lock(out, shard)), _logging_to(out):
        return _render_part(config, out, (k + n * worker, n * workers), refs, reconstruct, progress)


def _run_workers(config: DatasetConfig, out: Path, shard: tuple[int, int], refs: Sequence[ShapeRef],
                 reconstruct: Reconstruct | None, workers: int, bar: Any) -> dict[str, Any]:
    target = functools.partial(_worker, config, out, shard, refs, reconstruct, workers)
    results, failures, totals = run_workers(target, workers, bar, "render-dataset-worker", log=log.error)
    summary: dict[str, Any] = {"views_total": sum(t for t, _ in totals.values()),
                               "views_before": sum(b for _, b in totals.values()),
                               "views_rendered": sum(r["views_rendered"] for r in results.values()),
                               "skipped_shapes": {}}
    for result in results.values():
        summary["skipped_shapes"].update(result["skipped_shapes"])
    if failures:
        summary["failed_workers"] = {str(j): reason for j, reason in sorted(failures.items())}
    return summary


def _render_part(config: DatasetConfig, out: Path, shard: tuple[int, int], refs: Sequence[ShapeRef],
                 reconstruct: Reconstruct | None, progress: Any) -> dict[str, Any]:
    """Render the missing views of one shard in this process, reporting to ``progress``."""
    items = source_items(refs) if reconstruct is None else autoencoded_items(refs, reconstruct)
    mine = [(i, item) for i, item in enumerate(items) if i % shard[1] == shard[0]]
    done = set(manifest_records(out))  # every manifest: another shard or worker count may have rendered some
    total = len(mine) * config.views
    before = sum((item.id, v) in done for _, item in mine for v in range(config.views))
    progress.start(total, before)
    summary: dict[str, Any] = {"views_total": total, "views_before": before, "views_rendered": 0, "skipped_shapes": {}}
    versions = {"ngp_mi": __version__, **backend.versions(), "python": platform.python_version()}
    writer = BackgroundWriter(ManifestWriter(out / f"manifest{_shard_suffix(shard)}.jsonl"))
    try:
        for index, item in mine:
            todo = [v for v in range(config.views) if (item.id, v) not in done]
            if not todo:
                continue
            try:
                summary["views_rendered"] += _render_shape(config, out, index, item, todo, writer, versions, progress)
            except Exception as exc:  # a bad shape is skipped with its reason, the job goes on
                reason = f"{type(exc).__name__}: {exc}"
                log.warning("skipping %s (%s): %s", item.id, item.origin, reason)
                summary["skipped_shapes"][item.id] = reason
                progress.update(len(todo))
    finally:
        writer.close()
    return summary


def _render_shape(config: DatasetConfig, out: Path, index: int, item: SourceItem, views: Sequence[int],
                  writer: BackgroundWriter, versions: dict[str, str], progress: Any) -> int:
    content = item.load()
    cameras = config.cameras(index)
    if config.real_spp and config.lights == "scene" and not content.emitters:
        raise ValueError("--lights scene needs emitters in the scene file")
    # the mask is always rendered: it gives the stored rectangle (the data window) of every file
    channels = config.channels if "mask" in config.channels else (*config.channels, "mask")
    gbuffer = GBufferRenderer(content.shapes, content.bounds, cameras[0], channels)
    all_maps = gbuffer.render_views([cameras[v] for v in views])
    if not all_maps["mask"].any():
        raise ValueError(f"no view sees the object (0 object pixels in {len(views)} views): "
                         "is it centred at the origin within radius 0.5?")
    windows = [None] * len(views) if config.full_window else nonzero_windows(all_maps["mask"])
    real_scene = None
    for j, view in enumerate(views):
        camera = cameras[view]
        lights = config.view_lights(index, view)
        stem = f"{item.id}/{view:03d}"
        maps = {name: all_maps[name][j] for name in config.channels}
        window = windows[j]
        files = {"maps": f"maps/{stem}.exr"}
        image = None
        if config.real_spp:
            if real_scene is None or config.lights == "random":
                emitters = content.emitters if config.lights == "scene" else lights_to_mitsuba(lights)
                real_scene = build_scene(camera, {**content.shapes, **emitters}, (), {"type": "path", "max_depth": 6},
                                         spp=config.real_spp, pixel_format="rgba")
            else:
                set_sensor_camera(real_scene.sensors()[0], camera)
            image = render(real_scene, seed=derived_seed(config.seed, index, view))  # RGB + coverage
            files["real"] = f"real/{stem}.exr"
            files["real_png"] = f"real/{stem}.png"

        def write(maps=maps, window=window, image=image, files=files, view=view) -> None:
            write_exr(out / files["maps"], maps, config.compression, window=window,
                      metadata={"ngp_mi.shape_id": item.id, "ngp_mi.view": str(view)},
                      half=[c for c in maps if c != "depth"] if config.half else ())
            if image is not None:
                write_exr(out / files["real"], {"rgb": image[..., :3], "alpha": image[..., 3]}, config.compression)
                save_png(out / files["real_png"], to_uint8(image[..., :3]))

        writer.submit(write, {
            "shape_id": item.id, "source": item.kind, "origin": item.origin, "shape_index": index, "view": view,
            "theta_deg": camera.theta_deg, "phi_deg": camera.phi_deg, "K": camera.K.tolist(), "E": camera.E.tolist(),
            "width": camera.width, "height": camera.height, "channels": list(config.channels),
            "lights": [l.to_dict() for l in lights] if config.lights != "scene" else "scene",
            "seed": config.seed, "real_spp": config.real_spp, "files": files, "bounds": content.bounds.tolist(),
            "shape": content.meta, "versions": versions,
        }, lambda: progress.update(1))
    return len(views)
