"""The frame of the house: package boundaries, config handling, atomic outputs."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import jsonschema
import pytest
import yaml

from refflow.config import deep_merge, load_config
from refflow.io import atomic_path, config_hash, source_digest, write_json

ROOT = Path(__file__).resolve().parents[2]

# package -> packages it must never import (STYLE.md "three boundaries")
FORBIDDEN = {"flow": {"sim", "analysis"}, "sim": {"flow"}, "analysis": {"flow", "sim"},
             "refflow": {"flow", "sim", "analysis"}}  # the shared package stands below all three


def _imported_top_levels(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_boundaries(package):
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"package {package} has no modules"
    offenders = {
        str(f.relative_to(ROOT)): sorted(_imported_top_levels(f) & FORBIDDEN[package])
        for f in files
        if _imported_top_levels(f) & FORBIDDEN[package]
    }
    assert not offenders, f"{package} imports what it must not: {offenders}"


def test_deep_merge_overrides_nested_and_replaces_lists():
    base = {"beam": {"length_mm": 1000, "width_mm": 100}, "excitation": [{"type": "pluck"}]}
    merged = deep_merge(base, {"beam": {"length_mm": 500}, "excitation": [{"type": "ambient"}]})
    assert merged == {"beam": {"length_mm": 500, "width_mm": 100},
                      "excitation": [{"type": "ambient"}]}
    assert base["beam"]["length_mm"] == 1000, "the defaults must not be modified"


@pytest.mark.parametrize("name", ["config.yaml", "ci.yaml"])
def test_shipped_configs_match_schema(name):
    schema = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())
    config = yaml.safe_load((ROOT / "config" / name).read_text())
    jsonschema.validate(config, schema)


def test_schema_rejects_config_without_scenarios():
    schema = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())
    with pytest.raises(jsonschema.ValidationError, match="scenarios"):
        jsonschema.validate({"methods": ["dis"], "defaults": {"seed": 1, "duration_s": 1}}, schema)


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.csv"
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []


def test_atomic_path_renames_on_success_and_keeps_suffix(tmp_path):
    target = tmp_path / "sub" / "out.csv"
    with atomic_path(target) as tmp:
        assert tmp.suffix == ".csv"
        tmp.write_text("a,b\n")
    assert target.read_text() == "a,b\n"
    assert list(target.parent.iterdir()) == [target]


def test_write_json_is_sorted_and_rejects_nan(tmp_path):
    write_json(tmp_path / "a.json", {"b": 1, "a": [1.5]})
    assert json.loads((tmp_path / "a.json").read_text()) == {"a": [1.5], "b": 1}
    with pytest.raises(ValueError):
        write_json(tmp_path / "nan.json", {"x": float("nan")})
    assert not (tmp_path / "nan.json").exists()


def test_config_hash_ignores_key_order():
    assert config_hash({"a": 1, "b": {"c": 2}}) == config_hash({"b": {"c": 2}, "a": 1})
    assert config_hash({"a": 1}) != config_hash({"a": 2})


def test_load_config_names_the_problem(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "list.yaml"
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(ValueError, match="must hold a mapping"):
        load_config(bad)


def test_atomic_path_gives_ordinary_permissions(tmp_path):
    import os

    target = tmp_path / "out.txt"
    with atomic_path(target) as tmp:
        tmp.write_text("x")
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask


def test_source_digest_moves_with_the_code_it_names_only(tmp_path):
    """The workflow's rules take the digest of the code they run as a param, so that a changed
    tool re-runs its jobs: the digest must change with the package's (or refflow's) sources
    and with nothing else."""
    for name in ("flow", "sim", "refflow"):
        (tmp_path / name / "sub").mkdir(parents=True)
        (tmp_path / name / "a.py").write_text("x = 1\n")
        (tmp_path / name / "sub" / "b.py").write_text("y = 2\n")
    before = source_digest(tmp_path, "flow")
    assert source_digest(tmp_path, "flow") == before
    (tmp_path / "sim" / "a.py").write_text("x = 3\n")  # another stage's code
    (tmp_path / "flow" / "notes.txt").write_text("not code\n")
    assert source_digest(tmp_path, "flow") == before
    (tmp_path / "flow" / "sub" / "b.py").write_text("y = 3\n")
    changed = source_digest(tmp_path, "flow")
    assert changed != before
    (tmp_path / "refflow" / "a.py").write_text("x = 4\n")  # the shared plumbing
    assert source_digest(tmp_path, "flow") != changed
    (tmp_path / "flow" / "sub" / "b.py").rename(tmp_path / "flow" / "b.py")  # a file moved
    moved = source_digest(tmp_path, "flow")
    assert moved != changed
    (tmp_path / "flow" / "gui").mkdir()  # the browser page: no workflow stage runs it
    (tmp_path / "flow" / "gui" / "server.py").write_text("z = 5\n")
    assert source_digest(tmp_path, "flow") == moved
