"""`ngp-mi generate`: images, the maps sheet, every sweep, settings that re-run it, and the report."""

import json

import numpy as np
import pytest
from PIL import Image

from ngp_mi.cli import main
from ngp_mi.lights import DirectionalLight, save_lights


@pytest.fixture
def box_view(box_obj):
    return box_obj


def test_generate_writes_images_sheet_and_report(runs, box_view, tmp_path, capsys):
    maps_run, shape_run = runs
    lights = tmp_path / "lights.json"
    save_lights(lights, [DirectionalLight((0.0, 1.0, 1.0), (1.5, 1.5, 1.5))])
    code = main(["generate", "--maps-run", str(maps_run), "--shape-run", str(shape_run), "--out", str(tmp_path / "g"),
                 "--num", "2", "--views", "10,-30;15,40", "--res", "32", "--variant", "ngp-plus", "--add-lights", str(lights)])
    assert code == 0
    summary = json.loads((tmp_path / "g" / "generate.json").read_text())
    assert summary["variant"] == "ngp_plus" and len(summary["added_lights"]) == 1
    files = [tmp_path / "g" / r["file"] for r in summary["images"]]
    assert len(files) <= 4 and all(f.stat().st_size > 0 for f in files)
    assert (tmp_path / "g" / "sheet.png").exists() and "![sheet](sheet.png)" in (tmp_path / "g" / "report.md").read_text()
    # a user mesh and an exemplar albedo image instead of sampled latents
    from PIL import Image

    Image.fromarray(np.full((32, 32, 3), 180, np.uint8)).save(tmp_path / "albedo.png")
    assert main(["generate", "--maps-run", str(maps_run), "--mesh", str(box_view), "--out", str(tmp_path / "m"),
                 "--views", "5,0", "--res", "32", "--exemplar", str(tmp_path / "albedo.png")]) == 0
    assert [r["shape"] for r in json.loads((tmp_path / "m" / "generate.json").read_text())["images"]] == ["mesh"]
    assert main(["generate", "--maps-run", str(maps_run), "--out", str(tmp_path / "x")]) != 0
    assert "--shape-run" in capsys.readouterr().err


def test_every_sweep_is_a_labelled_sheet_and_the_run_can_be_repeated(runs, box_view, tmp_path):
    maps_run, shape_run = runs
    argv = ["generate", "--maps-run", str(maps_run), "--shape-run", str(shape_run), "--out", str(tmp_path / "s"),
            "--num", "1", "--views", "10,-30", "--res", "32", "--orbit-camera", "4", "--orbit-light", "3",
            "--appearance-seeds", "1,2", "--shape-seeds", "0,1,2", "--light-count", "1,4", "--interpolate", "0", "1",
            "--steps", "3", "--animate"]
    assert main(argv) == 0
    summary = json.loads((tmp_path / "s" / "generate.json").read_text())
    assert set(summary["sweep_files"]) == {"orbit_camera", "orbit_camera_animation", "orbit_light",
                                           "orbit_light_animation", "light_count", "appearance", "shapes",
                                           "interpolation"}
    widths = {}
    for name, file in summary["sweep_files"].items():
        path = tmp_path / "s" / file
        assert path.stat().st_size > 0, name
        if file.endswith(".png"):
            widths[name] = Image.open(path).width
    # one column per value (a header each), 32 px tiles + 4 px gaps after the 96 px row labels
    assert widths["orbit_camera"] == 96 + 4 * 36 + 4 and widths["shapes"] == 96 + 3 * 36 + 4
    assert widths["light_count"] == 96 + 2 * 36 + 4 and widths["interpolation"] == 96 + 3 * 36 + 4
    import imageio.v3 as iio

    assert iio.imread(tmp_path / "s" / "sweeps" / "orbit_camera.gif").shape[0] == 4 + 2  # there and back
    # the scene re-ran only what each sweep changes: 13 images need 13 shadings but fewer projections
    runs_ = summary["stage_runs"]
    assert runs_["shade"] == runs_["blend"] == 1 + 4 + 3 + 2 + 2 + 3 + 3
    assert runs_["extract"] <= 1 + 2 + 4  # the base shape, shape seeds 1 and 2, the interpolation
    assert runs_["project"] <= runs_["extract"] + 4 + 1 + 1 < runs_["shade"]  # + the orbit's views and the way back
    assert summary["command"][:2] == ["ngp-mi", "generate"] and "--orbit-light" in summary["command"]
    report = (tmp_path / "s" / "report.md").read_text()
    assert "Re-run: `ngp-mi generate" in report and "![orbit_light](sweeps/orbit_light.png)" in report
    # the recorded command re-runs it: the same images
    again = summary["command"][1:]
    again[again.index("--out") + 1] = str(tmp_path / "again")
    assert main(again) == 0
    for file in ("sheet.png", "sweeps/orbit_light.png", "sweeps/interpolation.png"):
        assert np.array_equal(np.asarray(Image.open(tmp_path / "s" / file)),
                              np.asarray(Image.open(tmp_path / "again" / file))), file


def test_exemplar_view_fits_z_da_to_a_dataset_view(runs, box_view, tmp_path, capsys):
    maps_run, _ = runs
    folder = tmp_path / "exemplars"
    assert main(["render-dataset", "--source", "chair", "--out", str(folder), "--num-shapes", "1", "--views", "2",
                 "--res", "32", "--channels", "albedo,depth,mask", "--real-spp", "0", "--quiet"]) == 0
    argv = ["generate", "--maps-run", str(maps_run), "--mesh", str(box_view), "--views", "5,0", "--res", "32",
            "--exemplar-view", str(folder), "--exemplar-item", "1", "--fit-steps", "3"]
    assert main([*argv, "--out", str(tmp_path / "v")]) == 0
    summary = json.loads((tmp_path / "v" / "generate.json").read_text())
    assert (summary["exemplar_view"], summary["exemplar_item"], summary["fit_steps"]) == (str(folder), 1, 3)
    assert "z_da fitted in 3 steps to view 1 of" in (tmp_path / "v" / "report.md").read_text()
    # the fitted code is not E_da's: 0 steps paints another albedo
    assert main([*argv[:-2], "--fit-steps", "0", "--out", str(tmp_path / "mu")]) == 0
    fitted, mu = (np.asarray(Image.open(tmp_path / d / "sheet.png")) for d in ("v", "mu"))
    assert not np.array_equal(fitted, mu)
    capsys.readouterr()
    # bad input names what is wrong
    assert main([*argv[:-4], "--exemplar-item", "2", "--out", str(tmp_path / "x")]) != 0
    assert "exemplar item 2 is out of range; the folder has 2 views" in capsys.readouterr().err
    assert main([*argv, "--exemplar", str(tmp_path / "a.png"), "--out", str(tmp_path / "x")]) != 0
    assert "not both" in capsys.readouterr().err
    depth_only = tmp_path / "depth_only"
    assert main(["render-dataset", "--source", "chair", "--out", str(depth_only), "--num-shapes", "1", "--views", "1",
                 "--res", "32", "--channels", "depth,mask", "--real-spp", "0", "--quiet"]) == 0
    assert main([*argv[:-6], "--exemplar-view", str(depth_only), "--out", str(tmp_path / "x")]) != 0
    assert "['albedo']" in capsys.readouterr().err
