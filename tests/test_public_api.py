"""Every name the packages export resolves (the lazy re-exports cannot rot silently)."""

import ast
import importlib
import importlib.util
from pathlib import Path

import pytest


@pytest.mark.parametrize("package", ["calib", "recon"])
def test_all_exports_resolve(package):
    mod = importlib.import_module(package)
    assert mod.__all__
    for name in mod.__all__:
        assert getattr(mod, name) is not None, name
    with pytest.raises(AttributeError):
        _ = mod.no_such_name


@pytest.mark.parametrize("package", ["recon", "calib"])
def test_package_modules_import_no_private_names_from_each_other(package):
    """What one module of a package needs from another has a public name (issue 11)."""
    root = Path(importlib.import_module(package).__file__).parent
    found = []
    for path in sorted(root.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and (node.level > 0 or (node.module or "").startswith(package)):
                found += [f"{path.name}: {alias.name}" for alias in node.names if alias.name.startswith("_")]
    assert not found, found


def _calib_private_uses(tree: ast.AST) -> list[str]:
    """``from calib... import _x``, ``<calib module>._x`` and ``setattr(<calib module>, "_x", ...)`` in a tree."""
    modules = set()  # local names bound to calib modules
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == "calib" or alias.name.startswith("calib."):
                    modules.add(alias.asname or alias.name.split(".")[0])
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "calib":
            for alias in node.names:
                if alias.name.startswith("_"):
                    found.append(f"from {node.module} import {alias.name}")
                elif importlib.util.find_spec(f"{node.module}.{alias.name}") if node.module == "calib" else False:
                    modules.add(alias.asname or alias.name)
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            base = node.value
            while isinstance(base, ast.Attribute):
                base = base.value
            if isinstance(base, ast.Name) and base.id in modules:
                found.append(f"{ast.unparse(node)}")
        elif (isinstance(node, ast.Call) and len(node.args) >= 2 and isinstance(node.args[0], ast.Name)
              and node.args[0].id in modules and isinstance(node.args[1], ast.Constant)
              and str(node.args[1].value).startswith("_")):
            found.append(f"{ast.unparse(node.func)}({node.args[0].id}, {node.args[1].value!r})")
    return found


@pytest.mark.parametrize("folder", ["tests", "benchmarks", "turntable", "recon"])
def test_no_private_calib_names_used_outside_calib(folder):
    """Tests, benchmarks and the other packages use calib through public names only (issue 11)."""
    root = Path(__file__).resolve().parents[1] / folder
    found = []
    for path in sorted(root.rglob("*.py")):
        found += [f"{path.relative_to(root.parent)}: {use}"
                  for use in _calib_private_uses(ast.parse(path.read_text(encoding="utf-8")))]
    assert not found, found


def test_the_private_use_check_can_fail():
    """The check above finds each form it looks for."""
    src = ("import calib.sequence as cs\nfrom calib import refine\nfrom calib.refine import _geometry\n"
           "cs._wrap(1)\nrefine._Problem\nmonkeypatch.setattr(cs, '_single_view', None)\ncs.rot_y(1)\n")
    assert sorted(_calib_private_uses(ast.parse(src))) == sorted([
        "from calib.refine import _geometry", "cs._wrap", "refine._Problem", "monkeypatch.setattr(cs, '_single_view')"])
