"""ngp-mi sample-shapes: meshes, sheet, interpolations, a missing run."""

import json

import numpy as np

from ngp_mi.cli import main


def test_sample_shapes_cli_writes_meshes_sheet_and_interpolations(tiny_run, tmp_path):
    run, _ = tiny_run
    out = tmp_path / "samples"
    assert main(["sample-shapes", "--run", str(run), "--out", str(out), "--num", "3", "--resolution", "32",
                 "--spp", "4"]) == 0
    summary = json.loads((out / "samples.json").read_text())
    files = [r["file"] for r in summary["shapes"] if r["file"]]
    assert files and all((out / f).stat().st_size > 0 for f in files)
    assert (out / "sheet.png").exists() and "sheet.png" in (out / "report.md").read_text()
    inter = tmp_path / "inter"
    assert main(["sample-shapes", "--run", str(run), "--out", str(inter), "--interpolate", "0", "2", "--steps", "3",
                 "--resolution", "32", "--format", "ply", "--spp", "4"]) == 0
    import trimesh
    # t = 0 and t = 1 are the shapes of seeds 0 and 2.
    for k, seed_file in ((0, "shape-000.obj"), (2, "shape-002.obj")):
        a = trimesh.load(inter / f"shape-{k:03d}.ply", process=False)
        b = trimesh.load(out / seed_file, process=False)
        np.testing.assert_allclose(np.asarray(a.vertices), np.asarray(b.vertices), atol=1e-5)
    assert main(["sample-shapes", "--run", str(tmp_path / "nothing"), "--out", str(out)]) == 1
