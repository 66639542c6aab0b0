"""Manifests: a torn last line (a killed writer) is ignored and trimmed, shards are read together, errors surface."""

import json

import pytest

from ngp_mi.data.manifest import BackgroundWriter, ManifestWriter, load_manifest, manifest_records, read_jsonl


def record(shape, view):
    return {"shape_id": shape, "view": view}


def test_a_torn_line_is_ignored_by_readers_and_trimmed_by_the_next_writer(tmp_path):
    path = tmp_path / "manifest.jsonl"
    path.write_text(json.dumps(record("a", 0)) + "\n" + '{"shape_id": "a", "vi')
    assert read_jsonl(path) == [record("a", 0)]
    writer = ManifestWriter(path)
    writer.append(record("a", 1))
    writer.close()
    assert read_jsonl(path) == [record("a", 0), record("a", 1)] and path.read_text().count("\n") == 2


def test_every_shards_manifest_is_read_and_sorted(tmp_path):
    (tmp_path / "manifest.shard-1-of-2.jsonl").write_text(json.dumps(record("b", 0)) + "\n")
    (tmp_path / "manifest.shard-0-of-2.jsonl").write_text(json.dumps(record("a", 1)) + "\n" + json.dumps(record("a", 0)) + "\n")
    assert [(r["shape_id"], r["view"]) for r in load_manifest(tmp_path)] == [("a", 0), ("a", 1), ("b", 0)]
    assert set(manifest_records(tmp_path)) == {("a", 0), ("a", 1), ("b", 0)}
    with pytest.raises(ValueError, match="no manifest"):
        load_manifest(tmp_path / "empty")


def test_a_record_follows_its_files_and_a_failed_write_stops_the_job(tmp_path):
    writer = BackgroundWriter(ManifestWriter(tmp_path / "manifest.jsonl"), threads=2)
    done = []
    for view in range(5):
        writer.submit(lambda v=view: (tmp_path / f"{v}.txt").write_text("x"), record("a", view), lambda: done.append(1))
    writer.close()
    assert len(done) == 5 and all((tmp_path / f"{r['view']}.txt").exists() for r in load_manifest(tmp_path))

    def disk_full():
        raise OSError("No space left on device")

    writer = BackgroundWriter(ManifestWriter(tmp_path / "manifest.jsonl"), threads=1)
    writer.submit(disk_full, record("b", 0), lambda: None)
    with pytest.raises(OSError, match="No space left"):
        writer.close()
    assert ("b", 0) not in manifest_records(tmp_path)  # no record for a view whose files were not written
