"""Every name the packages export resolves (the lazy re-exports cannot rot silently)."""

import ast
import importlib
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


def test_recon_modules_import_no_private_names_from_each_other():
    """What one recon module needs from another has a public name (issue 11)."""
    root = Path(importlib.import_module("recon").__file__).parent
    found = []
    for path in sorted(root.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and (node.level > 0 or (node.module or "").startswith("recon")):
                found += [f"{path.name}: {alias.name}" for alias in node.names if alias.name.startswith("_")]
    assert not found, found
