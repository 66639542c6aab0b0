"""ngp-mi demo and families: contact sheets of path-traced procedural objects."""

import json

import numpy as np
from helpers import run_cli
from PIL import Image

from ngp_mi.commands.demo import run_demo


def test_demo_writes_contact_sheets(tmp_path):
    sheet = run_demo(tmp_path, resolution=32, views=3, spp=4, family_count=2, log=lambda *_: None)
    image = np.asarray(Image.open(sheet))
    assert image.shape[0] > 32 and image.shape[1] > 4 * 32
    assert image.max() > 100  # something lit is in it
    meta = json.loads((tmp_path / "views.json").read_text())
    assert len(meta["cameras"]) == 3 and len(meta["lights"]) == 4 and meta["object"] == "chair/000000"
    for family in ("chair", "car"):
        assert np.asarray(Image.open(tmp_path / f"{family}.png")).max() > 50


def test_families_command_writes_a_sheet(tmp_path):
    out = tmp_path / "cars.png"
    done = run_cli("families", "car", "--count", "2", "--res", "24", "--spp", "2", "--out", str(out))
    assert done.returncode == 0, done.stderr
    assert Image.open(out).size[0] > 2 * 24
