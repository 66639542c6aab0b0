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


def test_files_that_share_a_stem_get_ids_that_keep_their_suffix(tmp_path):
    _box().export(tmp_path / "a.obj")
    _box(size=0.5).export(tmp_path / "a.stl")
    _box().export(tmp_path / "b.ply")
    found = find_meshes(tmp_path)
    assert [(m.id, m.path.name) for m in found] == [("a.obj", "a.obj"), ("a.stl", "a.stl"), ("b", "b.ply")]


@pytest.mark.parametrize("scale, offset", [(1e30, 0.0), (1e-30, 0.0), (1.0, 1e6), (1e3, 1e9)])
def test_huge_tiny_and_far_offset_meshes_normalise_exactly(tmp_path, scale, offset):
    """Normalised in float64: the same shape as the mesh at the origin, whatever its scale and place."""
    mesh = _box()
    reference = load_mesh(_write_obj(mesh, tmp_path / "ref.obj"))
    mesh.apply_scale(scale)
    mesh.apply_translation((offset, -offset, 0.5 * offset))
    moved = load_mesh(_write_obj(mesh, tmp_path / "box.obj"))
    np.testing.assert_allclose(moved.vertices, reference.vertices, atol=1e-6)


def test_meshes_that_cannot_be_normalised_are_refused_with_the_reason(tmp_path):
    path = tmp_path / "far.obj"
    path.write_text("v 1e200 0 0\nv 0 1e200 0\nv 0 0 1e200\nf 1 2 3\n")
    with pytest.raises(MeshError, match=r"far.obj: .*(cannot be normalised|coincide)"):
        load_mesh(path)


def test_text_meshes_in_another_encoding_load(tmp_path):
    path = tmp_path / "latin.obj"
    path.write_bytes("# chaise longue, café\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".encode("latin-1"))
    assert len(load_mesh(path).faces) == 1


def test_a_truncated_binary_stl_says_so(tmp_path):
    whole = _export(_box(), tmp_path / "box.stl")
    cut = tmp_path / "cut.stl"
    cut.write_bytes(whole.read_bytes()[:300])
    with pytest.raises(MeshError, match=r"cut.stl: truncated binary STL: its header announces 12 triangles \(684 bytes\), "
                                        r"the file has 300 bytes"):
        load_mesh(cut)
    (tmp_path / "tiny.stl").write_bytes(b"\x00" * 20)
    with pytest.raises(MeshError, match="less than a binary STL's 84-byte header"):
        load_mesh(tmp_path / "tiny.stl")
    assert len(load_mesh(whole).faces) == 12


def _export(mesh, path):
    mesh.export(path)
    return path


def _write_obj(mesh, path):
    """An OBJ with every digit of float64 (exporters round to float32 or 8 digits)."""
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in mesh.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    path.write_text("\n".join(lines) + "\n")
    return path
