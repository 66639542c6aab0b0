"""Dataset sources: families, mesh files and folders, scene files, and coarse (autoencoded) shapes."""

import dataclasses

import numpy as np
import pytest
import torch
import trimesh

from ngp_mi.data.datasets import ReflectanceMapDataset
from ngp_mi.data.render_dataset import DatasetConfig, render_dataset
from ngp_mi.data.sources import resolve_source
from ngp_mi.models.shape import CoarseShapes


def test_render_dataset_of_autoencoded_shapes_pairs_with_the_detailed_views(tiny_run, tmp_path):
    """--coarse-shapes: same ids and cameras as the detailed dataset, other geometry (the reconstruction)."""
    run, _ = tiny_run
    config = DatasetConfig(source="chair", num_shapes=2, views=2, resolution=32, channels=("depth", "mask"))
    render_dataset(config, tmp_path / "detailed", progress=False)
    summary = render_dataset(dataclasses.replace(config, coarse_shapes=str(run), coarse_resolution=32),
                             tmp_path / "coarse", progress=False, reconstruct=CoarseShapes(run, 32))
    detailed, coarse = ReflectanceMapDataset(tmp_path / "detailed"), ReflectanceMapDataset(tmp_path / "coarse")
    rendered = {(r["shape_id"], r["view"]) for r in coarse.records}
    assert len(rendered) + 2 * len(summary["skipped_shapes"]) == 4
    assert all("empty shape" in reason for reason in summary["skipped_shapes"].values())
    for i, record in enumerate(detailed.records):
        if (record["shape_id"], record["view"]) not in rendered:
            continue
        j = next(j for j, r in enumerate(coarse.records) if (r["shape_id"], r["view"]) == (record["shape_id"], record["view"]))
        assert np.allclose(record["K"], coarse.records[j]["K"]) and np.allclose(record["E"], coarse.records[j]["E"])
        a, b = detailed[i], coarse[j]
        assert b["mask"].sum() > 0 and not torch.equal(a["depth"], b["depth"])
    with pytest.raises(ValueError, match="not a scene file"):
        render_dataset(dataclasses.replace(config, source="scenes/table_lamp.xml", coarse_shapes=str(run)), tmp_path / "s",
                       progress=False, reconstruct=CoarseShapes(run))


def test_items_load_lazily_and_a_bad_mesh_fails_with_its_reason(tmp_path):
    trimesh.creation.box(extents=(0.5, 0.4, 0.3)).export(tmp_path / "box.obj")
    (tmp_path / "broken.obj").write_text("this is not a mesh\n")
    items = resolve_source(str(tmp_path), 5)  # nothing is read yet
    assert [(i.id, i.kind) for i in items] == [("box", "mesh"), ("broken", "mesh")]
    content = items[0].load()
    assert len(content.shapes) == 1 and np.isclose(np.linalg.norm(content.bounds[1]), 0.5, atol=1e-4)  # normalised
    with pytest.raises(ValueError, match="broken.obj"):
        items[1].load()
    (lamp,) = resolve_source("scenes/table_lamp.xml", 1)
    assert lamp.kind == "scene" and lamp.load().emitters


def test_coarse_shapes_need_their_reconstruction(tmp_path):
    config = DatasetConfig(source="chair", num_shapes=1, views=1, resolution=16, coarse_shapes="some/run")
    with pytest.raises(ValueError, match="coarse_shapes and reconstruct go together"):
        render_dataset(config, tmp_path, progress=False)


def test_coarse_shapes_of_a_shipped_model(tmp_path):
    """--coarse-shapes chair: the shipped model's G_shape reconstructs the shapes (what `evaluate maps
    --coarse-data` scores a shipped model on); a name that is neither a run nor a model fails up front."""
    import pickle

    from helpers import run_cli

    from ngp_mi.models.pretrained import load_shape

    config = DatasetConfig(source="chair", num_shapes=1, views=1, resolution=32, channels=("depth", "mask"))
    render_dataset(config, tmp_path / "detailed", progress=False)
    reconstruct = pickle.loads(pickle.dumps(CoarseShapes("chair", 32, load=load_shape)))  # as workers receive it
    summary = render_dataset(dataclasses.replace(config, coarse_shapes="chair", coarse_resolution=32),
                             tmp_path / "coarse", progress=False, reconstruct=reconstruct)
    assert summary["views_rendered"] == 1, summary["skipped_shapes"]
    detailed, coarse = ReflectanceMapDataset(tmp_path / "detailed")[0], ReflectanceMapDataset(tmp_path / "coarse")[0]
    assert coarse["mask"].sum() > 0 and not torch.equal(detailed["depth"], coarse["depth"])

    def box(mask: torch.Tensor) -> torch.Tensor:  # rows and columns the object spans (thin legs: masks barely overlap)
        rows, cols = torch.nonzero(mask[0] > 0, as_tuple=True)
        return torch.stack([rows.min(), rows.max(), cols.min(), cols.max()])

    assert (box(detailed["mask"]) - box(coarse["mask"])).abs().max() <= 3  # the same chair, where the camera sees it
    done = run_cli("render-dataset", "--source", "chair", "--num-shapes", "1", "--views", "1", "--res", "16",
                   "--out", str(tmp_path / "x"), "--coarse-shapes", "no_such_model")
    assert done.returncode == 1 and "'no_such_model': not a shipped model (car, chair" in done.stderr
