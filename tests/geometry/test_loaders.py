import numpy as np
import pytest
import trimesh

from ngp_mi.geometry import NORMALIZED_RADIUS
from ngp_mi.geometry.loaders import MeshError, find_meshes, load_mesh


def _box(offset=(0.0, 0.0, 0.0), size=1.0):
    mesh = trimesh.creation.box(extents=(size, 2 * size, 3 * size))
    mesh.apply_translation(offset)
    return mesh


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".off", ".stl", ".glb"])
def test_formats_load_and_normalise(tmp_path, suffix):
    path = tmp_path / f"box{suffix}"
    _box((3.0, -1.0, 2.0)).export(path)
    mesh = load_mesh(path)
    assert len(mesh.faces) == 12
    assert np.linalg.norm(mesh.vertices, axis=1).max() == pytest.approx(NORMALIZED_RADIUS, rel=1e-5)
    lo, hi = mesh.bounds
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-6)
    raw = load_mesh(path, normalize=False)
    np.testing.assert_allclose(raw.bounds.mean(0), [3.0, -1.0, 2.0], atol=1e-5)


def test_multi_part_file_keeps_a_part_id_per_face(tmp_path):
    scene = trimesh.Scene()
    scene.add_geometry(_box(), node_name="seat", geom_name="seat")
    scene.add_geometry(_box((2.0, 0.0, 0.0), 0.5), node_name="leg", geom_name="leg")
    path = tmp_path / "two.glb"
    scene.export(path)
    mesh = load_mesh(path)
    assert sorted(np.unique(mesh.part_ids)) == [0, 1]
    assert np.bincount(mesh.part_ids).tolist() == [12, 12]


@pytest.mark.parametrize("content, reason", [
    ("", "empty mesh|contains no triangles"),
    ("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", "not finite"),
    ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "degenerate"),
])
def test_bad_obj_files_give_a_reason(tmp_path, content, reason):
    path = tmp_path / "bad.obj"
    path.write_text(content)
    with pytest.raises(MeshError, match=reason) as info:
        load_mesh(path)
    assert str(path) in str(info.value)


def test_unreadable_and_missing_files(tmp_path):
    path = tmp_path / "garbage.glb"
    path.write_bytes(b"\x00\x01 not a mesh at all")
    with pytest.raises(MeshError, match="garbage.glb"):
        load_mesh(path)
    with pytest.raises(MeshError, match="no such file"):
        load_mesh(tmp_path / "nothing.obj")


def test_degenerate_faces_are_dropped(tmp_path):
    path = tmp_path / "mixed.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nf 1 2 3\nf 1 2 4\n")
    assert len(load_mesh(path).faces) == 1


def test_find_meshes_in_shapenet_tree_and_plain_folder(tmp_path):
    for synset, model in [("03001627", "aaa"), ("03001627", "bbb"), ("02958343", "ccc")]:
        folder = tmp_path / "shapenet" / synset / model / "models"
        folder.mkdir(parents=True)
        _box().export(folder / "model_normalized.obj")
    ids = [s.id for s in find_meshes(tmp_path / "shapenet")]
    assert ids == ["02958343/ccc", "03001627/aaa", "03001627/bbb"]
    plain = tmp_path / "plain"
    (plain / "sub").mkdir(parents=True)
    _box().export(plain / "a.ply")
    _box().export(plain / "sub" / "b.STL")
    (plain / "notes.txt").write_text("not a mesh")
    assert [s.id for s in find_meshes(plain)] == ["a", "sub/b"]
    with pytest.raises(ValueError, match="not a folder"):
        find_meshes(tmp_path / "missing")
