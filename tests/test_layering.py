"""The import arrows of DESIGN.md section 1, checked on the syntax tree of every module."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIRST_PARTY = {"pointmap", "data", "training", "export", "benchmarks", "tests"}

# package -> first-party modules it may import (prefix match)
ALLOWED = {
    "pointmap": ("pointmap",),
    "data": ("data", "pointmap.geometry", "pointmap.errors"),
    "training": ("training", "pointmap", "data"),
    "export": ("export", "pointmap"),
}


def imports_of(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.lineno, node.module
        elif isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", "")) == "import_module":
            if node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
                yield node.lineno, node.args[0].value


def violations(package: str):
    allowed = ALLOWED[package]
    found = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for line, mod in imports_of(path):
            top = mod.split(".")[0]
            if top in FIRST_PARTY and not any(mod == a or mod.startswith(a + ".") for a in allowed):
                found.append(f"{path.relative_to(ROOT)}:{line} imports {mod}")
    return found


def test_the_library_imports_only_itself_among_first_party_packages():
    assert violations("pointmap") == []


def test_the_data_engine_imports_only_geometry_and_errors_from_the_library():
    assert violations("data") == []


def test_training_imports_only_the_library_and_the_data_engine():
    assert violations("training") == []


def test_export_imports_only_the_library():
    assert violations("export") == []


def test_the_checker_catches_a_forbidden_import(tmp_path, monkeypatch):
    pkg = tmp_path / "pointmap"
    pkg.mkdir()
    (pkg / "bad.py").write_text("import training.loop\nfrom data import scene\n")
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    assert len(violations("pointmap")) == 2


def test_no_eval_or_exec_anywhere():
    bad = []
    for package in ("pointmap", "data", "training", "export"):
        for path in (ROOT / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Call) and getattr(node.func, "id", None) in ("eval", "exec"):
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert bad == []


def test_no_lazily_exported_function_or_class_shares_its_name_with_a_submodule():
    """Importing pointmap.X binds the module X on the package, so a lazy export named X that is not the module itself
    would turn into that module after first use (it once did: pm.localize)."""
    import pointmap

    clashes = [name for name, module in pointmap._LAZY.items()
               if module != f"pointmap.{name}" and ((ROOT / "pointmap" / f"{name}.py").exists()
                                                   or (ROOT / "pointmap" / name / "__init__.py").exists())]
    assert clashes == []
