"""The frame of the house: package boundaries, config handling, atomic outputs."""

from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import jsonschema
import pytest
import yaml

from refflow.config import deep_merge, load_config
from refflow.io import atomic_path, config_hash, source_digest, write_json

sys.path.insert(0, str(Path(__file__).parent))
from _fresh_python import run_fresh  # noqa: E402

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


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(tree: ast.AST, *, deferred: bool) -> list[ast.Import | ast.ImportFrom]:
    """The import statements of a module: those run when it is imported, and with
    ``deferred`` also those inside functions (run when the function is first called)."""
    found, stack = [], list(ast.iter_child_nodes(tree))
    while stack:
        node = stack.pop()
        if isinstance(node, ast.Import | ast.ImportFrom):
            found.append(node)
        if deferred or not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            stack.extend(ast.iter_child_nodes(node))
    return found


def _flow_import_graph(*, deferred: bool) -> dict[str, set[str]]:
    """``{module: modules of flow it imports}`` over flow/**/*.py.

    Importing ``a.b.c`` first runs the packages ``a`` and ``a.b`` (their ``__init__``): those
    count too, except the importer's own packages (already running when it runs); ``from p
    import x`` imports the module ``p.x`` where there is one."""
    paths = {_module_name(p): p for p in sorted((ROOT / "flow").rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for module, path in paths.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        targets: set[str] = set()
        for node in _imports(ast.parse(path.read_text(), filename=str(path)), deferred=deferred):
            if isinstance(node, ast.Import):
                named = [alias.name for alias in node.names]
            else:
                base = node.module or ""
                if node.level:
                    above = package.split(".")[:len(package.split(".")) - node.level + 1]
                    base = ".".join(above + ([base] if base else []))
                named = [f"{base}.{a.name}" if f"{base}.{a.name}" in paths else base for a in node.names]
            for name in named:
                parts = name.split(".")
                for depth in range(1, len(parts) + 1):
                    target = ".".join(parts[:depth])
                    own_package = module == target or module.startswith(target + ".")
                    if target in paths and (target == name or not own_package) and target != module:
                        targets.add(target)
        graph[module] = targets
    return graph


def _circle_through(graph: dict[str, set[str]], start: str) -> list[str] | None:
    """A shortest chain of imports from ``start`` back to ``start``, or None."""
    came_from: dict[str, str] = {}
    frontier = [start]
    while frontier:
        following = []
        for module in frontier:
            for target in sorted(graph[module]):
                if target == start:
                    chain = [module]
                    while chain[-1] != start:
                        chain.append(came_from[chain[-1]])
                    return [start, *reversed(chain[:-1]), start]
                if target not in came_from:
                    came_from[target] = module
                    following.append(target)
        frontier = following
    return None


def test_flow_modules_import_in_no_circle():
    # A module importing one that (through others) imports it back sees it half-built
    # ("cannot import name ... from partially initialized module"), depending on which of
    # the two a caller happened to import first.
    graph = _flow_import_graph(deferred=False)
    circles = {" -> ".join(c) for m in graph if (c := _circle_through(graph, m))}
    assert not circles, f"flow's modules import in a circle: {sorted(circles)}"


# Issue 34: the layout shows the design. The readers (flow/io/), the measurement every method
# shares (flow/measure/) and the methods (flow/methods/, one folder for a method with its own
# kernels) are sub-packages; the application (CLI, pipeline, options, outputs, the other
# commands, gui/) sits at the top and is the only part that sees them all.
MAX_TOP_MODULES = 12
MAX_INIT_LINES = 40
# flow's sub-package -> the others it may import (nothing from the application at the top)
LAYERS = {"io": set(), "measure": {"io"}, "methods": {"io", "measure"}}


def test_flow_top_holds_the_application_only():
    top = sorted(p.name for p in (ROOT / "flow").glob("*.py"))
    assert len(top) <= MAX_TOP_MODULES, (
        f"{len(top)} modules directly in flow/ (at most {MAX_TOP_MODULES}): {top}; a reader "
        "belongs in flow/io/, a step of the measurement in flow/measure/, a method or its "
        "kernels in flow/methods/")
    packages = sorted(p.parent.name for p in (ROOT / "flow").glob("*/__init__.py"))
    assert {"io", "measure", "methods", "gui"} <= set(packages), packages


def test_flow_inits_are_short():
    # A package's __init__ says what is inside; code lives in its modules.
    long = {str(p.relative_to(ROOT)): n for p in sorted((ROOT / "flow").rglob("__init__.py"))
            if (n := len(p.read_text().splitlines())) > MAX_INIT_LINES}
    assert not long, f"__init__.py over {MAX_INIT_LINES} lines: {long}"


def _part(module: str) -> str:
    """The sub-package of LAYERS a module of flow belongs to, else "application"."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else "application"


def test_flow_sub_packages_import_only_the_layers_below():
    # Even from inside a function: the readers know nothing of the measurement, the
    # measurement nothing of a method (the driver gets one as an argument), and none of
    # them anything of the application above them.
    graph = _flow_import_graph(deferred=True)
    crossing = sorted(f"{module} -> {target}" for module, targets in graph.items()
                      if _part(module) in LAYERS for target in targets
                      if target != "flow" and _part(target) != _part(module)
                      and _part(target) not in LAYERS[_part(module)])
    assert not crossing, f"imports against the layers {LAYERS}: {crossing}"


def test_registry_and_methods_import_in_no_circle_even_on_demand():
    # STYLE.md "Base classes apart from the registry": a method module imports the base, the
    # registry loads the methods (on first use) and imports the base; neither way back, not
    # even from inside a function.
    graph = _flow_import_graph(deferred=True)
    ours = [m for m in graph if m.split(".")[:2] == ["flow", "methods"]]
    circles = {" -> ".join(c) for m in ours if (c := _circle_through(graph, m))}
    assert not circles, f"the registry and the methods import in a circle: {sorted(circles)}"


# The modules that register methods (a method with its own kernels is a folder: its module
# that registers, not the kernels).
METHOD_MODULES = ["flow.methods.registry", "flow.methods", "flow.methods.base", *(
    _module_name(p) for p in sorted((ROOT / "flow" / "methods").rglob("*.py"))
    if p.name != "base.py" and re.search(r"^@register\(", p.read_text(), re.MULTILINE))]
# Each module first, each pair of modules both ways round.
IMPORT_ORDERS = [pytest.param(names[i:] + names[:i], id=f"{names[i]}-first-{way}")
                 for way, names in (("forward", METHOD_MODULES), ("backward", METHOD_MODULES[::-1]))
                 for i in range(len(names))]


@pytest.mark.parametrize("order", IMPORT_ORDERS)
def test_registry_and_methods_import_in_any_order(order):
    # In a fresh interpreter; then the registry knows every built-in method.
    from flow.methods import registry

    code = ("import importlib\n"
            f"for name in {order!r}:\n    importlib.import_module(name)\n"
            "from flow.methods import registry\nprint(','.join(registry.available()))\n")
    run = run_fresh(code)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == [",".join(registry.available())]


def test_the_command_line_starts_without_the_spectral_libraries():
    # Every `refflow` command imports flow.cli and its subcommands' parsers; scipy.signal (with
    # scipy.stats under it, a second or two on a 2-core machine) is imported only by the code
    # that picks peaks or identifies modes, when it runs.
    run = run_fresh("import sys\nimport flow.cli\n"
                    "print(sorted(m for m in sys.modules if m.startswith(('scipy.signal', 'scipy.stats'))))")
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["[]"], run.stdout


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


def test_load_config_reads_yaml_json_and_empty_files(tmp_path):
    (tmp_path / "a.yaml").write_text("seed: 7\nbeam: {length_mm: 1000}\n")
    assert load_config(tmp_path / "a.yaml") == {"seed": 7, "beam": {"length_mm": 1000}}
    (tmp_path / "b.json").write_text('{"rate": 1e5}')
    assert load_config(tmp_path / "b.json") == {"rate": 100000.0}  # YAML 1.1 reads "1e5" as text
    (tmp_path / "empty.yaml").write_text("")
    assert load_config(tmp_path / "empty.yaml") == {}
    (tmp_path / "bad.yaml").write_text("a: [1, 2\n")
    with pytest.raises(ValueError, match="bad.yaml is not valid YAML"):
        load_config(tmp_path / "bad.yaml")


@pytest.mark.parametrize("argv", [["-m", "sim", "modes", "--config", "{missing}"],
                                  ["-m", "sim", "render", "figures", "--config", "{missing}"],
                                  ["-m", "analysis", "gates", "m.json", "--gates", "{missing}"]])
def test_every_package_reads_configs_through_the_one_loader(tmp_path, argv):
    """sim, its renderer and analysis name a missing config file in the one loader's words."""
    missing = str(tmp_path / "missing.yaml")
    run = subprocess.run([sys.executable, *[a.format(missing=missing) for a in argv]], cwd=ROOT,
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert run.returncode == 2, run.stderr[-2000:]
    assert f"error: config file {missing} does not exist" in run.stderr


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


# Issue 15: no function over 100 lines in any package (numba kernels included: none is).
SHORT_FUNCTION_PACKAGES = ("analysis", "refflow", "flow", "sim")


@pytest.mark.parametrize("package", SHORT_FUNCTION_PACKAGES)
def test_no_function_over_100_lines(package):
    long = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > 100:
                    long[f"{path.relative_to(ROOT)}:{node.name}"] = lines
    assert not long, f"functions over 100 lines: {long}"


@pytest.mark.parametrize("interrupted_at", [0, 1, 2])
def test_atomic_paths_takes_back_a_rename_interrupted_as_it_returns(tmp_path, monkeypatch, interrupted_at):
    """Ctrl-C just after a rename returned, before the set noted it: that file is taken back
    with the others (the run left one file of three on disk, saying it wrote them); a file of
    the set not renamed yet keeps its earlier version."""
    import refflow.io as rio
    from refflow.io import atomic_paths

    finals = [tmp_path / name for name in ("a.npz", "b.json", "c.csv")]
    finals[2].write_text("earlier")
    renamed = []
    publish = rio._publish

    def interrupted(tmp, final):
        publish(tmp, final)
        renamed.append(final)
        if len(renamed) == interrupted_at + 1:
            raise KeyboardInterrupt

    monkeypatch.setattr(rio, "_publish", interrupted)
    with pytest.raises(KeyboardInterrupt), atomic_paths(*finals) as temporaries:
        for tmp in temporaries:
            tmp.write_text("new")
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == ([] if interrupted_at == 2 else ["c.csv"]), left
    if interrupted_at < 2:
        assert finals[2].read_text() == "earlier"


def test_atomic_paths_keeps_an_earlier_file_whose_replacement_was_interrupted(tmp_path, monkeypatch):
    """Ctrl-C before the last rename (its chmod): the earlier version of that file stays, the
    files of the set already renamed are taken back, no temporary is left."""
    import refflow.io as rio
    from refflow.io import atomic_paths

    finals = [tmp_path / "a.json", tmp_path / "c.csv"]
    finals[1].write_text("earlier")
    publish = rio._publish

    def interrupted(tmp, final):
        if final.name == "c.csv":
            raise KeyboardInterrupt
        publish(tmp, final)

    monkeypatch.setattr(rio, "_publish", interrupted)
    with pytest.raises(KeyboardInterrupt), atomic_paths(*finals) as temporaries:
        for tmp in temporaries:
            tmp.write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.csv"]
    assert finals[1].read_text() == "earlier"
