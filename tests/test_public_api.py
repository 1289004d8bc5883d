"""Every name the packages export resolves (the lazy re-exports cannot rot silently)."""

import importlib

import pytest


@pytest.mark.parametrize("package", ["calib", "recon"])
def test_all_exports_resolve(package):
    mod = importlib.import_module(package)
    assert mod.__all__
    for name in mod.__all__:
        assert getattr(mod, name) is not None, name
    with pytest.raises(AttributeError):
        getattr(mod, "no_such_name")
