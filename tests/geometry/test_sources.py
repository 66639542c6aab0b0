"""The one source resolver: families, mesh files and folders, scene files; solids of families and meshes."""

import numpy as np
import pytest
import trimesh

from ngp_mi.geometry.occupancy import grid_points, load_solid
from ngp_mi.geometry.sources import ShapeRef, resolve_shapes


def test_a_family_gives_seeded_ids(tmp_path):
    refs = resolve_shapes("car", 3, seed=7)
    assert [r.id for r in refs] == ["car/000007", "car/000008", "car/000009"]
    assert {r.kind for r in refs} == {"procedural"} and refs[2].seed == 9


def test_files_folders_and_scenes(tmp_path):
    trimesh.creation.box().export(tmp_path / "b.obj")
    trimesh.creation.icosphere().export(tmp_path / "a.ply")
    assert [(r.id, r.kind) for r in resolve_shapes(str(tmp_path), 5)] == [("a", "mesh"), ("b", "mesh")]
    assert [r.id for r in resolve_shapes(str(tmp_path), 1)] == ["a"]
    assert resolve_shapes(str(tmp_path / "b.obj"), 1)[0].path == tmp_path / "b.obj"
    (tmp_path / "room.xml").write_text("<scene version='3.0.0'/>")
    assert [r.kind for r in resolve_shapes(str(tmp_path), 5)] == ["scene"]  # a folder of scenes is a scene source
    assert [r.kind for r in resolve_shapes(str(tmp_path), 5, scenes=False)] == ["mesh", "mesh"]


@pytest.mark.parametrize("source, scenes, message", [
    ("sofa", True, r"--source 'sofa': not a family \(car, chair\), file or folder"),
    ("README.md", True, r"README.md: not a mesh \(.obj.*\) or Mitsuba scene \(.xml\)"),
    ("scenes/table_lamp.xml", False, r"table_lamp.xml: not a mesh \(.obj.*\)$"),
])
def test_bad_sources_are_named(source, scenes, message):
    with pytest.raises(ValueError, match=message):
        resolve_shapes(source, 1, scenes=scenes)
    with pytest.raises(ValueError, match="num_shapes must be >= 1"):
        resolve_shapes("chair", 0)


def test_solids_of_a_family_and_of_its_mesh_agree(tmp_path):
    (ref,) = resolve_shapes("chair", 1, seed=4)
    solid = load_solid(ref)
    path = tmp_path / "chair.obj"
    trimesh.Trimesh(solid.mesh.vertices, solid.mesh.faces, process=False).export(path)
    from_file = load_solid(ShapeRef("chair", "mesh", str(path), path=path))  # winding numbers of the same surface
    points = grid_points(24).reshape(-1, 3)
    assert np.mean(solid.inside(points) == from_file.inside(points)) > 0.99
    assert solid.grid(16).shape == (16, 16, 16) and solid.grid(16).any()
    with pytest.raises(ValueError, match="not a solid"):
        load_solid(ShapeRef("lamp", "scene", "scenes/table_lamp.xml"))
