import json
import subprocess
import sys

import numpy as np
from ngp_mi.commands.demo import run_demo
from PIL import Image


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "ngp_mi.cli", *args], capture_output=True, text=True, timeout=300)


def test_help_lists_subcommands_with_descriptions():
    done = _cli("--help")
    assert done.returncode == 0
    for command in ("doctor", "demo", "families"):
        line = next(l for l in done.stdout.splitlines() if l.strip().startswith(command + " "))
        assert len(line.split()) > 3, f"no description for {command}: {line!r}"


def test_doctor_reports_and_renders():
    done = _cli("doctor")
    assert done.returncode == 0, done.stdout + done.stderr
    for key in ("python", "torch", "mitsuba   3.9.1", "drjit     1.5.0", "variant", "libLLVM", "threads", "64x64 ok"):
        assert key in done.stdout


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
    done = _cli("families", "car", "--count", "2", "--res", "24", "--spp", "2", "--out", str(out))
    assert done.returncode == 0, done.stderr
    assert Image.open(out).size[0] > 2 * 24
