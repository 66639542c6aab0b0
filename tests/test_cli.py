"""The ngp-mi command: sub-commands with descriptions, flags whose defaults are their configs', a fast start."""

import subprocess
import sys

from helpers import run_cli

from ngp_mi.cli import build_parser
from ngp_mi.data.render_dataset import DatasetConfig
from ngp_mi.eval.compare import CompareConfig


def test_help_lists_subcommands_with_descriptions():
    done = run_cli("--help")
    assert done.returncode == 0
    for command in ("doctor", "demo", "families"):
        line = next(l for l in done.stdout.splitlines() if l.strip().startswith(command + " "))
        assert len(line.split()) > 3, f"no description for {command}: {line!r}"


def test_flag_defaults_are_the_config_defaults():
    args = build_parser("render-dataset").parse_args(["render-dataset", "--source", "chair", "--out", "x"])
    d = DatasetConfig(source="chair")
    assert (args.num_shapes, args.views, args.res, args.compression, args.lights, args.coarse_resolution) == \
        (d.num_shapes, d.views, d.resolution, d.compression, d.lights, d.coarse_resolution)
    assert tuple(args.channels.split(",")) == d.channels
    args = build_parser("compare").parse_args(["compare", "--out", "x"])
    c = CompareConfig()
    assert (args.spp_ladder, args.reference_spp, tuple(args.lights.split(",")), args.res) == \
        (c.spp_ladder, c.reference_spp, c.light_setups, c.resolution)


def test_sample_counts_of_zero_are_refused_where_the_flag_is_read():
    for argv in (["families", "car", "--spp", "0"], ["compare", "--out", "x", "--spp-ladder", "4,0"],
                 ["compare", "--out", "x", "--reference-spp", "0"]):
        done = run_cli(*argv)
        assert done.returncode == 2 and "must be >= 1, got 0" in done.stderr


def test_generate_names_the_sizes_the_networks_take():
    done = run_cli("generate", "--maps-run", "any", "--out", "x", "--res", "30")
    assert done.returncode == 2 and "--res: invalid network_size value" not in done.stderr
    assert "size 30x30: the map networks take image sizes that are multiples of 4" in done.stderr
    assert "nearest: 28 or 32" in done.stderr


def test_help_and_light_commands_start_without_torch():
    code = ("import sys; from ngp_mi.cli import main\ntry: main(['--help'])\nexcept SystemExit: pass\n"
            "print('torch' in sys.modules, 'mitsuba' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.stdout.strip().splitlines()[-1] == "False False"
