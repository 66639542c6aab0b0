"""ngp-mi render-dataset: layout, manifest, determinism, resume, shards, bad input, scene files."""

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import trimesh
from helpers import ROOT, ExitingReconstruct, rss_mib

from ngp_mi.data.exr import read_exr
from ngp_mi.data.render_dataset import DatasetConfig, check_memory, load_manifest, parse_shard, render_dataset


def run(out, **kwargs):
    config = DatasetConfig(**{"source": "chair", "num_shapes": 2, "views": 2, "resolution": 24, **kwargs})
    return render_dataset(config, out, progress=False)


def test_layout_manifest_and_files(tmp_path):
    summary = run(tmp_path, real_spp=4)
    assert summary["views_rendered"] == 4 and not summary["skipped_shapes"]
    records = load_manifest(tmp_path)
    assert [(r["shape_id"], r["view"]) for r in records] == [
        ("chair/000000", 0), ("chair/000000", 1), ("chair/000001", 0), ("chair/000001", 1)]
    r = records[0]
    for key in ("theta_deg", "phi_deg", "K", "E", "lights", "seed", "width", "channels", "versions", "shape"):
        assert key in r
    assert 0 <= r["theta_deg"] <= 20 and -90 <= r["phi_deg"] <= 90 and len(r["lights"]) == 4
    maps = read_exr(tmp_path / r["files"]["maps"])
    assert set(maps) == {"depth", "normal", "albedo", "noc", "mask"} and maps["depth"].shape == (24, 24)
    real = read_exr(tmp_path / r["files"]["real"])["rgb"]
    assert real.shape == (24, 24, 3) and real.max() > 0
    assert (tmp_path / r["files"]["real_png"]).exists()
    assert json.loads((tmp_path / "summary.json").read_text())["views_rendered"] == 4


def test_the_real_images_alpha_is_the_pixels_coverage(tmp_path):
    """alpha against an independent coverage: the true chair's Π_v at 8 × 8 sub-pixel centres, pooled."""
    import torch

    from ngp_mi.camera import Camera
    from ngp_mi.geometry.families import generate
    from ngp_mi.render.depth import supersampled_depth_coverage

    run(tmp_path, num_shapes=1, views=1, resolution=32, real_spp=256)
    r = load_manifest(tmp_path)[0]
    alpha = read_exr(tmp_path / r["files"]["real"])["alpha"]
    mask = read_exr(tmp_path / r["files"]["maps"])["mask"]
    truth = generate("chair", 0).mesh()
    camera = Camera.from_K_E(np.asarray(r["K"]), np.asarray(r["E"]), r["width"], r["height"])
    coverage = supersampled_depth_coverage(torch.as_tensor(truth.vertices, dtype=torch.float32), truth.faces,
                                           camera, 8)[1][0, 0].numpy()
    edge = (coverage > 0.02) & (coverage < 0.98)
    assert edge.sum() > 20 and ((alpha > 0.02) & (alpha < 0.98)).sum() > 20  # soft where the outline crosses
    assert np.abs(alpha - coverage).max() < 0.2 and np.abs(alpha - coverage)[edge].mean() < 0.05
    assert np.array_equal(alpha[~edge] > 0.5, mask[~edge] > 0.5)  # and the mask's value away from it


def test_same_seed_same_files(tmp_path):
    run(tmp_path / "a", real_spp=2)
    run(tmp_path / "b", real_spp=2)
    for r_a, r_b in zip(load_manifest(tmp_path / "a"), load_manifest(tmp_path / "b")):
        assert (r_a["K"], r_a["E"]) == (r_b["K"], r_b["E"])
        for key in ("maps", "real"):
            a, b = read_exr(tmp_path / "a" / r_a["files"][key]), read_exr(tmp_path / "b" / r_b["files"][key])
            for channel in a:
                np.testing.assert_array_equal(a[channel], b[channel])
    other = DatasetConfig(source="chair", num_shapes=2, views=2, resolution=24, seed=1)
    render_dataset(other, tmp_path / "c", progress=False)
    assert load_manifest(tmp_path / "c")[0]["E"] != load_manifest(tmp_path / "a")[0]["E"]


def test_resume_renders_only_what_is_missing(tmp_path):
    run(tmp_path, views=3)
    manifest = tmp_path / "manifest.jsonl"
    lines = manifest.read_text().splitlines()
    manifest.write_text("\n".join(lines[:2]) + "\n" + lines[2][:40])  # killed while appending line 3
    summary = run(tmp_path, views=3)
    assert summary["views_before"] == 2 and summary["views_rendered"] == 4
    records = load_manifest(tmp_path)
    assert len(records) == 6 and len(manifest.read_text().splitlines()) == 6


def test_resume_with_other_settings_is_refused(tmp_path):
    run(tmp_path)
    with pytest.raises(ValueError, match=r"other settings \(resolution\)"):
        run(tmp_path, resolution=32)


def test_shards_split_the_work_and_merge(tmp_path):
    config = DatasetConfig(source="car", num_shapes=3, views=2, resolution=16)
    render_dataset(config, tmp_path / "whole", progress=False)
    for k in range(2):
        render_dataset(config, tmp_path / "sharded", shard=(k, 2), progress=False)
    assert sorted(p.name for p in (tmp_path / "sharded").glob("manifest*.jsonl")) == [
        "manifest.shard-0-of-2.jsonl", "manifest.shard-1-of-2.jsonl"]
    whole, sharded = load_manifest(tmp_path / "whole"), load_manifest(tmp_path / "sharded")
    assert [(r["shape_id"], r["view"], r["E"]) for r in whole] == [(r["shape_id"], r["view"], r["E"]) for r in sharded]
    np.testing.assert_array_equal(read_exr(tmp_path / "whole" / whole[-1]["files"]["maps"])["depth"],
                                  read_exr(tmp_path / "sharded" / sharded[-1]["files"]["maps"])["depth"])
    with pytest.raises(ValueError, match="K/N"):
        parse_shard("2/2")


def maps_of(root):
    """Every view's maps by (shape id, view), read through read_exr (display-window arrays)."""
    return {(r["shape_id"], r["view"]): read_exr(root / r["files"]["maps"]) for r in load_manifest(root)}


def assert_same_maps(a, b):
    assert a.keys() == b.keys()
    for key in a:
        for channel in a[key]:
            np.testing.assert_array_equal(a[key][channel], b[key][channel], err_msg=f"{key} {channel}")


def test_maps_are_stored_in_the_object_rectangle(tmp_path):
    import OpenEXR

    run(tmp_path / "window")
    run(tmp_path / "full", full_window=True)
    record = load_manifest(tmp_path / "window")[0]
    header = OpenEXR.File(str(tmp_path / "window" / record["files"]["maps"])).header()
    (x0, y0), (x1, y1) = (list(c) for c in header["dataWindow"])
    mask = read_exr(tmp_path / "window" / record["files"]["maps"])["mask"]
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    assert (x0, y0, x1, y1) == (cols[0], rows[0], cols[-1], rows[-1]) and (x1 - x0 + 1) * (y1 - y0 + 1) < 24 * 24
    assert_same_maps(maps_of(tmp_path / "window"), maps_of(tmp_path / "full"))


def test_a_resume_may_change_how_maps_are_stored(tmp_path):
    """Codec and window are storage, not content: a resumed folder may mix them; other settings may not."""
    run(tmp_path / "ref", views=3)
    run(tmp_path / "mixed", views=3)
    manifest = tmp_path / "mixed" / "manifest.jsonl"
    manifest.write_text("\n".join(manifest.read_text().splitlines()[:2]) + "\n")
    summary = run(tmp_path / "mixed", views=3, compression="zip", full_window=True)
    assert summary["views_before"] == 2 and summary["views_rendered"] == 4
    assert_same_maps(maps_of(tmp_path / "mixed"), maps_of(tmp_path / "ref"))
    with pytest.raises(ValueError, match=r"other settings \(views\)"):
        run(tmp_path / "mixed", views=4, compression="zip")


def test_worker_processes_write_what_one_process_writes(tmp_path):
    config = DatasetConfig(source="chair", num_shapes=3, views=2, resolution=20, real_spp=2)
    render_dataset(config, tmp_path / "one", progress=False)
    summary = render_dataset(config, tmp_path / "two", progress=False, workers=2)
    assert summary["views_rendered"] == 6 and summary["workers"] == 2 and not summary["skipped_shapes"]
    assert sorted(p.name for p in (tmp_path / "two").glob("manifest*.jsonl")) == [
        "manifest.shard-0-of-2.jsonl", "manifest.shard-1-of-2.jsonl"]
    assert_same_maps(maps_of(tmp_path / "two"), maps_of(tmp_path / "one"))
    one, two = load_manifest(tmp_path / "one"), load_manifest(tmp_path / "two")
    assert [(r["shape_id"], r["view"], r["E"], r["lights"]) for r in one] == [
        (r["shape_id"], r["view"], r["E"], r["lights"]) for r in two]
    for a, b in zip(one, two):
        np.testing.assert_array_equal(read_exr(tmp_path / "one" / a["files"]["real"])["rgb"],
                                      read_exr(tmp_path / "two" / b["files"]["real"])["rgb"])
    again = render_dataset(config, tmp_path / "two", progress=False)  # another worker count resumes it
    assert again["views_before"] == 6 and again["views_rendered"] == 0


def test_shards_started_together_share_one_folder(tmp_path):
    cli = [sys.executable, "-m", "ngp_mi.cli", "render-dataset", "--source", "car", "--num-shapes", "4",
           "--views", "1", "--res", "16", "--workers", "1", "--quiet", "--out", str(tmp_path)]
    shards = [subprocess.Popen(cli + ["--shard", f"{k}/2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True) for k in range(2)]
    for shard in shards:
        _, err = shard.communicate(timeout=300)
        assert shard.returncode == 0, err
    assert len(load_manifest(tmp_path)) == 4 and not list(tmp_path.glob(".dataset.*"))


def _mesh_folder(tmp_path):
    folder = tmp_path / "meshes"
    folder.mkdir()
    trimesh.creation.box(extents=(1, 2, 1)).export(folder / "good.obj")
    (folder / "bad.obj").write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    return folder


def test_bad_mesh_is_skipped_with_reason_and_strict_fails(tmp_path):
    folder = _mesh_folder(tmp_path)
    config = DatasetConfig(source=str(folder), num_shapes=10, views=2, resolution=16)
    summary = render_dataset(config, tmp_path / "out", progress=False)
    assert summary["views_rendered"] == 2
    assert list(summary["skipped_shapes"]) == ["bad"] and "not finite" in summary["skipped_shapes"]["bad"]
    assert "bad.obj" in (tmp_path / "out" / "render-dataset.log").read_text()
    cli = [sys.executable, "-m", "ngp_mi.cli", "render-dataset", "--source", str(folder), "--views", "1",
           "--res", "16", "--quiet"]
    done = subprocess.run(cli + ["--out", str(tmp_path / "cli")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "skipped bad" in done.stdout
    done = subprocess.run(cli + ["--out", str(tmp_path / "strict"), "--strict"], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode != 0 and "--strict" in done.stderr


def test_half_precision_keeps_depth_in_float32(tmp_path):
    run(tmp_path / "full")
    run(tmp_path / "half", half=True)
    import OpenEXR

    record = load_manifest(tmp_path / "half")[0]
    parts = OpenEXR.File(str(tmp_path / "half" / record["files"]["maps"])).channels()
    assert parts["depth"].pixels.dtype == np.float32 and parts["normal"].pixels.dtype == np.float16
    full = read_exr(tmp_path / "full" / record["files"]["maps"])
    half = read_exr(tmp_path / "half" / record["files"]["maps"])
    np.testing.assert_array_equal(half["depth"], full["depth"])
    np.testing.assert_allclose(half["noc"], full["noc"], atol=5e-4)


def test_only_requested_channels(tmp_path):
    run(tmp_path, channels=("depth", "mask"))
    record = load_manifest(tmp_path)[0]
    assert set(read_exr(tmp_path / record["files"]["maps"])) == {"depth", "mask"}
    with pytest.raises(ValueError, match="subset of"):
        DatasetConfig(source="chair", channels=("depth", "colour"))


SCENE_XML = """<scene version="3.0.0">
  <shape type="sphere"><float name="radius" value="0.35"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.3, 0.2"/></bsdf></shape>
  <emitter type="directional"><vector name="direction" value="0, -1, -1"/>
    <rgb name="irradiance" value="3, 3, 3"/></emitter>
</scene>"""


def test_scene_file_source_with_its_own_lights(tmp_path):
    (tmp_path / "ball.xml").write_text(SCENE_XML)
    (tmp_path / "empty.xml").write_text('<scene version="3.0.0"/>')
    config = DatasetConfig(source=str(tmp_path), num_shapes=5, views=2, resolution=24, real_spp=4, lights="scene")
    summary = render_dataset(config, tmp_path / "out", progress=False)
    assert summary["views_rendered"] == 2 and "no shapes" in summary["skipped_shapes"]["empty"]
    record = load_manifest(tmp_path / "out")[0]
    maps = read_exr(tmp_path / "out" / record["files"]["maps"])
    assert maps["mask"].sum() > 20
    np.testing.assert_allclose(maps["albedo"][maps["mask"] > 0], [[0.6, 0.3, 0.2]] * int(maps["mask"].sum()), atol=1e-6)
    assert read_exr(tmp_path / "out" / record["files"]["real"])["rgb"].max() > 0


def test_the_shipped_scene_files_render(tmp_path):

    scenes = ROOT / "scenes"
    config = DatasetConfig(source=str(scenes), num_shapes=10, views=1, resolution=24, real_spp=4, lights="scene")
    summary = render_dataset(config, tmp_path, progress=False)
    assert summary["views_rendered"] >= 1 and not summary["skipped_shapes"]
    for record in load_manifest(tmp_path):
        assert read_exr(tmp_path / record["files"]["maps"])["mask"].sum() > 10


# ----------------------------------------------------------------------------- long runs (make test-slow)

@pytest.mark.slow
def test_dataset_memory_stays_flat_over_2000_views(tmp_path):
    """200 shapes (a new Mitsuba scene each) x 10 views: resident memory must not grow."""
    samples = []
    for chunk in range(8):
        config = DatasetConfig(source="chair", num_shapes=25, views=10, resolution=64, seed=1000 * chunk)
        summary = render_dataset(config, tmp_path / str(chunk), progress=False)
        assert summary["views_rendered"] == 250
        samples.append(rss_mib())
    # 5 MiB: a kernel compiled per shape (a literal in the trace) grew it by 14 MiB over these views
    assert samples[-1] - samples[0] < 5, f"RSS after each 250 views: {samples}"


# ----------------------------------------------------------------------------- bad sources, memory, locks, kills

def test_the_source_is_checked_once_before_anything_is_written(tmp_path):
    for source, reason in ((tmp_path / "no-such-meshes", "not a family"), (tmp_path / "empty", "no meshes")):
        (tmp_path / "empty").mkdir(exist_ok=True)
        config = DatasetConfig(source=str(source), num_shapes=2, views=1, resolution=16)
        with pytest.raises(ValueError, match=reason):
            render_dataset(config, tmp_path / "out", progress=False, workers=2)
        assert not (tmp_path / "out").exists()
    summary = run(tmp_path / "out", num_shapes=1, views=1)  # the corrected command, into the same folder
    assert summary["views_rendered"] == 1


def test_a_job_that_renders_nothing_fails(tmp_path):
    (tmp_path / "scenes").mkdir()
    (tmp_path / "scenes" / "lights_only.xml").write_text(
        '<scene version="3.0.0"><emitter type="constant"/></scene>')
    (tmp_path / "scenes" / "far_away.xml").write_text(SCENE_XML.replace(
        '<float name="radius" value="0.35"/>', '<float name="radius" value="0.35"/><point name="center" x="0" y="40" z="0"/>'))
    config = DatasetConfig(source=str(tmp_path / "scenes"), num_shapes=5, views=2, resolution=16)
    with pytest.raises(RuntimeError, match="nothing was rendered: 2 shape"):
        render_dataset(config, tmp_path / "out", progress=False)
    skipped = json.loads((tmp_path / "out" / "summary.json").read_text())["skipped_shapes"]
    assert "no shapes" in skipped["lights_only"] and "no view sees the object" in skipped["far_away"]
    done = subprocess.run([sys.executable, "-m", "ngp_mi.cli", "render-dataset", "--source",
                           str(tmp_path / "scenes" / "lights_only.xml"), "--res", "16", "--quiet",
                           "--out", str(tmp_path / "cli")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 1 and "nothing was rendered" in done.stderr


def test_a_failing_worker_is_reported_by_name(tmp_path):
    config = DatasetConfig(source="chair", num_shapes=2, views=1, resolution=16, coarse_shapes="exiting")
    with pytest.raises(RuntimeError, match=r"2 worker\(s\) failed .*told to exit"):
        render_dataset(config, tmp_path / "out", progress=False, workers=2, reconstruct=ExitingReconstruct())
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert sorted(summary["failed_workers"]) == ["0", "1"] and summary["views_rendered"] == 0
    assert "worker 0 failed" in (tmp_path / "out" / "render-dataset.log").read_text()


def test_a_job_too_large_for_memory_is_refused_with_the_figure(tmp_path):
    for settings, reason in (({"resolution": 30000}, r"needs about 644\.0 GiB .*GiB are available"),
                             ({"views": 100000}, r"needs about \d+\.\d GiB \(1 process\(es\) x 100000 views"),
                             ({"resolution": 100000}, "more than the 4,294,967,295 a Dr.Jit launch holds")):
        config = DatasetConfig(source="chair", num_shapes=1, **settings)
        with pytest.raises(ValueError, match=reason):
            render_dataset(config, tmp_path / "out", progress=False)
        assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match=r"needs about 12\.0 GiB \(2 process"):
        check_memory(DatasetConfig(source="chair", views=64, resolution=1024), workers=2, available=1 << 30)


def test_the_memory_estimate_bounds_the_measured_peak(tmp_path):
    script = ("import resource, sys\n"
              "from ngp_mi.data.render_dataset import DatasetConfig, render_dataset\n"
              "c = DatasetConfig(source='chair', num_shapes=1, views=4, resolution=1536, real_spp=2)\n"
              "render_dataset(c, sys.argv[1], progress=False)\n"
              "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024, c.memory_needed())\n")
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True, timeout=300)
    peak, estimate = (int(x) for x in done.stdout.split())
    assert peak <= estimate <= 3 * peak, (peak >> 20, estimate >> 20)


def test_one_job_at_a_time_writes_a_shard(tmp_path, monkeypatch):
    from ngp_mi import lock
    from ngp_mi.data import render_dataset as module

    monkeypatch.setattr(module, "WORKERS_EXIT_SECONDS", 0.5)
    with lock.exclusive(tmp_path / "render-dataset.lock", "a test"):
        with pytest.raises(lock.Busy, match=rf"is being written by pid {os.getpid()} on .*since"):
            run(tmp_path)
        with pytest.raises(lock.Busy, match="earlier render-dataset job still write here"):
            with lock.shared(tmp_path / "render-dataset.shard-0-of-2.workers.lock"):  # a killed job's worker
                render_dataset(DatasetConfig(source="chair", num_shapes=2, views=1, resolution=16), tmp_path,
                               shard=(0, 2), progress=False)
        summary = render_dataset(DatasetConfig(source="chair", num_shapes=2, views=1, resolution=16), tmp_path,
                                 shard=(1, 2), progress=False)  # another shard is another lock
        assert summary["views_rendered"] == 1
    assert run(tmp_path, views=1, resolution=16)["views_rendered"] == 1  # released: shard 0 of 1 renders the missing view


def test_a_job_told_to_wait_renders_once_the_holder_is_done(tmp_path, capsys):
    """Training caches pass ``wait``: a job started beside another one on the same folder waits for it
    (saying whom it waits for) instead of failing; past its wait it fails as the CLI does."""
    import threading

    from ngp_mi import lock

    held, release = threading.Event(), threading.Event()

    def holder():
        with lock.exclusive(tmp_path / "render-dataset.lock", "a test"):
            held.set()
            release.wait(10)

    thread = threading.Thread(target=holder)
    thread.start()
    held.wait(10)
    config = DatasetConfig(source="chair", num_shapes=1, views=1, resolution=16)
    with pytest.raises(lock.Busy, match="is being written by"):
        render_dataset(config, tmp_path, progress=False, wait=0.3)
    threading.Timer(1.0, release.set).start()
    assert render_dataset(config, tmp_path, progress=False, wait=30)["views_rendered"] == 1
    thread.join()
    assert "waiting up to 30 s" in capsys.readouterr().err


def test_killing_the_job_stops_its_workers_and_a_rerun_renders_each_view_once(tmp_path):
    cli = [sys.executable, "-m", "ngp_mi.cli", "render-dataset", "--source", "chair", "--num-shapes", "12",
           "--views", "8", "--res", "48", "--real-spp", "64", "--workers", "2", "--quiet", "--out", str(tmp_path)]
    job = subprocess.Popen(cli, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def lines():
        return sum(len(p.read_text().splitlines()) for p in tmp_path.glob("manifest*.jsonl"))

    deadline = time.monotonic() + 120
    while not lines():
        assert time.monotonic() < deadline and job.poll() is None, "the job rendered nothing"
        time.sleep(0.05)
    job.kill()  # the main process alone, as subprocess.run(timeout=...) does
    job.wait()
    time.sleep(1)
    count = lines()
    time.sleep(1.5)
    assert lines() == count < 96, "the workers went on writing"
    assert subprocess.run(cli, capture_output=True, timeout=600).returncode == 0
    records = [(r["shape_id"], r["view"]) for r in load_manifest(tmp_path)]
    assert len(records) == len(set(records)) == 96


def test_a_folder_of_bad_meshes_beside_good_ones_renders_every_good_one_and_names_every_bad_one(tmp_path):
    folder = tmp_path / "meshes"
    folder.mkdir()

    def obj(mesh, comment="# a box"):
        return (comment + "\n" + "".join(f"v {x:.17g} {y:.17g} {z:.17g}\n" for x, y, z in mesh.vertices)
                + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in mesh.faces))

    box = trimesh.creation.box(extents=(1, 2, 1))
    box.export(folder / "box.obj")
    trimesh.creation.box(extents=(2, 1, 1)).export(folder / "box.stl")  # the same stem
    (folder / "latin.obj").write_bytes(obj(box, "# chaise longue, café").encode("latin-1"))
    (folder / "huge.obj").write_text(obj(box.copy().apply_scale(1e30)))
    (folder / "offset.obj").write_text(obj(box.copy().apply_translation((1e6, -1e6, 5e5))))
    (folder / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    (folder / "cut.stl").write_bytes((folder / "box.stl").read_bytes()[:300])
    (folder / "empty.obj").write_text("# nothing\n")
    (folder / "overflow.obj").write_text("v 1e200 0 0\nv 0 1e200 0\nv 0 0 1e200\nf 1 2 3\n")
    config = DatasetConfig(source=str(folder), num_shapes=20, views=2, resolution=24)
    summary = render_dataset(config, tmp_path / "out", progress=False, workers=2)
    rendered = {r["shape_id"] for r in load_manifest(tmp_path / "out")}
    assert rendered == {"box.obj", "box.stl", "latin", "huge", "offset"} and summary["views_rendered"] == 10
    skipped = summary["skipped_shapes"]
    assert sorted(skipped) == ["cut", "empty", "nan", "overflow"]
    assert "truncated binary STL" in skipped["cut"] and "not finite" in skipped["nan"]
    assert "overflow.obj" in skipped["overflow"] and "empty.obj" in skipped["empty"]
    log = (tmp_path / "out" / "render-dataset.log").read_text()
    assert all(f"skipping {name}" in log for name in skipped)
    masks = {r["shape_id"]: read_exr(tmp_path / "out" / r["files"]["maps"])["mask"] for r in load_manifest(tmp_path / "out")}
    assert all(m.sum() > 20 for m in masks.values())  # the huge and the far-offset box too
