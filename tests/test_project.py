"""The project directory contract: manifest, schema version, stage records, atomic writes."""

from __future__ import annotations

import json

import pytest

from avatarctl.atomic import atomic_dir, atomic_path, write_json
from avatarctl.errors import ProjectError
from avatarctl.project import SCHEMA_VERSION, BodyModelRef, Project, SourceRef, hash_tree


def _make(tmp_path):
    return Project.create(tmp_path / "p", body_model=BodyModelRef(name="anny", path=None),
                          source=SourceRef(path="/cap", format="easymocap", sha256="0" * 64, files=3))


def test_create_open_roundtrip(tmp_path):
    proj = _make(tmp_path)
    again = Project.open(proj.root)
    assert again.manifest.schema_version == SCHEMA_VERSION
    assert again.manifest.body_model.name == "anny"
    assert again.manifest.source.format == "easymocap"


def test_create_refuses_existing_project(tmp_path):
    _make(tmp_path)
    with pytest.raises(ProjectError, match="already exists"):
        _make(tmp_path)


def test_unknown_schema_version_is_actionable(tmp_path):
    proj = _make(tmp_path)
    data = json.loads(proj.paths.manifest.read_text())
    data["schema_version"] = 99
    proj.paths.manifest.write_text(json.dumps(data))
    with pytest.raises(ProjectError) as e:
        Project.open(proj.root)
    msg = str(e.value)
    assert "schema_version 99" in msg and "->" in msg and "\n" not in msg


def test_malformed_manifest(tmp_path):
    proj = _make(tmp_path)
    proj.paths.manifest.write_text("{not json")
    with pytest.raises(ProjectError, match="cannot read project manifest"):
        Project.open(proj.root)


def test_stage_record_and_missing_output(tmp_path):
    proj = _make(tmp_path)
    with pytest.raises(ProjectError, match="no fit output yet"):
        proj.require("fit")
    out = proj.paths.fit_config
    write_json(out, {"a": 1})
    proj.record("fit", {"iters": 3}, [out], started="2026-01-01T00:00:00+00:00", summary={"psnr": 20.0})
    rec = Project.open(proj.root).require("fit")
    assert rec.outputs == ["fit/config.json"] and rec.config == {"iters": 3}
    out.unlink()
    with pytest.raises(ProjectError, match="fit output is missing: fit/config.json"):
        Project.open(proj.root).require("fit")


def test_bad_render_name(tmp_path):
    proj = _make(tmp_path)
    with pytest.raises(ProjectError, match="invalid render name"):
        proj.paths.render("../escape")


def test_atomic_path_leaves_nothing_on_error(tmp_path):
    dest = tmp_path / "x.json"
    with pytest.raises(RuntimeError):
        with atomic_path(dest) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert not dest.exists()
    assert list(tmp_path.iterdir()) == []


def test_atomic_dir_replaces_only_when_complete(tmp_path):
    dest = tmp_path / "out"
    dest.mkdir()
    (dest / "old.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_dir(dest) as tmp:
            (tmp / "new.txt").write_text("new")
            raise RuntimeError("boom")
    assert (dest / "old.txt").read_text() == "old" and not (dest / "new.txt").exists()
    with atomic_dir(dest) as tmp:
        (tmp / "new.txt").write_text("new")
    assert sorted(p.name for p in dest.iterdir()) == ["new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_hash_tree_changes_with_content(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "f.txt").write_text("1")
    h1, n = hash_tree(tmp_path)
    (tmp_path / "a" / "f.txt").write_text("2")
    h2, _ = hash_tree(tmp_path)
    assert n == 1 and h1 != h2
