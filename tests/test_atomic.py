"""Atomic writes: a finished write replaces the file, a failed one leaves the old file and no temporary."""

import os
import stat

import pytest

from ngp_mi.atomic import atomic_path, write_json, write_text


def test_a_write_replaces_the_file_and_leaves_no_temporary(tmp_path):
    path = write_text(tmp_path / "a" / "notes.txt", "one")
    write_text(path, "two")
    assert path.read_text() == "two" and os.listdir(path.parent) == ["notes.txt"]
    assert stat.S_IMODE(path.stat().st_mode) & 0o044  # readable by others, as open() makes files (umask 022)


def test_a_failed_write_keeps_the_previous_file(tmp_path):
    path = write_json(tmp_path / "data.json", {"a": 1})
    with pytest.raises(RuntimeError):
        with atomic_path(path) as tmp:
            tmp.write_text("half a record")
            raise RuntimeError("killed")
    assert path.read_text() == '{\n "a": 1\n}\n' and os.listdir(tmp_path) == ["data.json"]


def test_the_temporary_keeps_the_suffix_and_folders_replace_folders(tmp_path):
    with atomic_path(tmp_path / "mesh.obj") as tmp:
        assert tmp.suffix == ".obj" and tmp.name.startswith(".mesh.obj.")  # writers that read the suffix
        tmp.write_text("v 0 0 0\n")
    folder = tmp_path / "ckpt-00000001"
    for text in ("old", "new"):
        with atomic_path(folder, directory=True) as tmp:
            (tmp / "state.txt").write_text(text)
    assert (folder / "state.txt").read_text() == "new"
    assert sorted(os.listdir(tmp_path)) == ["ckpt-00000001", "mesh.obj"]
    assert stat.S_IMODE(folder.stat().st_mode) & 0o055


def test_files_get_the_usual_permissions_whatever_the_writer_made(tmp_path):
    import os
    import stat

    from ngp_mi.atomic import _FILE_MODE, atomic_path

    with atomic_path(tmp_path / "weights.bin") as tmp:
        tmp.write_bytes(b"x")
        os.chmod(tmp, 0o600)  # what safetensors' writer leaves
    assert stat.S_IMODE((tmp_path / "weights.bin").stat().st_mode) == _FILE_MODE
