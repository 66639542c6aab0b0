"""Shared fixtures: the initialised backend, JIT clean-up between test modules, and tiny trained runs."""

from __future__ import annotations

import pytest
from helpers import maps_recipe, shape_recipe

from ngp_mi import backend
from ngp_mi.training.maps import train_maps
from ngp_mi.training.shape import train_shape


@pytest.fixture(scope="session")
def mi():
    """The ``mitsuba`` module with the project's variant set."""
    return backend.mitsuba()


@pytest.fixture(scope="module", autouse=True)
def _release_jit_memory():
    yield
    backend.jit_cleanup()


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A `train shape` run of the tiny recipe (trained once per session) and its folder."""
    tmp = tmp_path_factory.mktemp("shape")
    return train_shape(shape_recipe(tmp, "run"), log=lambda *_: None), tmp


@pytest.fixture(scope="session")
def tiny_maps_run(tmp_path_factory):
    """A `train maps` run of the tiny recipe cut to 2 map steps (+ its 3 G_sp^real steps), trained once."""
    return train_maps(maps_recipe(tmp_path_factory.mktemp("maps"), "run", iterations=2), log=lambda *_: None)


@pytest.fixture(scope="session")
def tiny_model(tiny_maps_run, tiny_run, tmp_path_factory):
    """The tiny runs exported as a model folder (what `--model` loads), family chair."""
    from ngp_mi.models.pretrained import export_model

    return export_model(tmp_path_factory.mktemp("model") / "chair_tiny", tiny_maps_run, tiny_run[0], family="chair",
                        figures={"iou_held_out": 0.5}, notes="a test")


@pytest.fixture(scope="session")
def box_obj(tmp_path_factory):
    """A box mesh file (0.6 x 0.5 x 0.4) a user might bring."""
    import trimesh

    path = tmp_path_factory.mktemp("mesh") / "box.obj"
    trimesh.creation.box(extents=(0.6, 0.5, 0.4)).export(path)
    return path


@pytest.fixture(scope="session")
def runs(tiny_maps_run, tiny_run):
    """(the tiny maps run, the tiny shape run)."""
    return tiny_maps_run, tiny_run[0]
