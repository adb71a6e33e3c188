"""The module names from before the sub-packages (mitsuba_powder._compat): each old name imports
as its new module, with a DeprecationWarning naming the new module; an old name whose module
file still exists is that file; an entry whose new module is missing does not import."""

from __future__ import annotations

import importlib
import importlib.machinery
import re
import sys

import pytest

import mitsuba_powder
from mitsuba_powder import _compat


def forget(monkeypatch, name: str) -> None:
    """Make the next ``import name`` go through the finders again (undone after the test)."""
    monkeypatch.delitem(sys.modules, name, raising=False)
    monkeypatch.delattr(mitsuba_powder, name.rpartition(".")[2], raising=False)


def has_file(name: str) -> bool:
    """Whether module ``name`` (directly under the package) is a file of the package."""
    leaf = name.rpartition(".")[2]
    return importlib.machinery.PathFinder.find_spec(leaf, mitsuba_powder.__path__) is not None


def test_old_module_is_the_new_one_with_a_warning(monkeypatch):
    forget(monkeypatch, "mitsuba_powder.fit")
    with pytest.warns(DeprecationWarning, match=r"mitsuba_powder\.fitting\.fit\b"):
        import mitsuba_powder.fit as old
    import mitsuba_powder.fitting.fit as new
    assert old is new
    assert sys.modules["mitsuba_powder.fit"] is new
    assert new.__name__ == new.__spec__.name == "mitsuba_powder.fitting.fit"


def test_from_old_module_import_a_name(monkeypatch):
    forget(monkeypatch, "mitsuba_powder.model")
    with pytest.warns(DeprecationWarning, match=r"mitsuba_powder\.plugin\.brf\b"):
        from mitsuba_powder.model import PowderBRF
    from mitsuba_powder.plugin.brf import PowderBRF as new
    assert PowderBRF is new


def test_from_package_import_old_module(monkeypatch):
    forget(monkeypatch, "mitsuba_powder.measurements")
    with pytest.warns(DeprecationWarning, match=r"mitsuba_powder\.io\.measurements\b"):
        from mitsuba_powder import measurements
    from mitsuba_powder.io.measurements import load_measurements
    assert measurements.load_measurements is load_measurements


@pytest.mark.parametrize("old,new", sorted(_compat.MOVED.items()))
def test_every_entry_imports(old, new, monkeypatch):
    if has_file(old):
        pytest.skip(f"{old} is still a module file: the entry is inactive")
    target = importlib.import_module(new)
    forget(monkeypatch, old)
    with pytest.warns(DeprecationWarning, match=re.escape(new) + r"\b"):
        module = importlib.import_module(old)
    assert module is target


def test_real_module_file_is_not_shadowed(monkeypatch):
    """An entry for a name that is a module file of the package: the file is imported."""
    monkeypatch.setitem(_compat.MOVED, "mitsuba_powder.outputs", "mitsuba_powder.variants")
    forget(monkeypatch, "mitsuba_powder.outputs")
    module = importlib.import_module("mitsuba_powder.outputs")
    assert module.__name__ == "mitsuba_powder.outputs"
    assert module is not importlib.import_module("mitsuba_powder.variants")


def test_entry_without_its_new_module_is_inactive(monkeypatch):
    monkeypatch.setitem(_compat.MOVED, "mitsuba_powder.no_such_old_module",
                        "mitsuba_powder.no_such_package.no_such_module")
    with pytest.raises(ModuleNotFoundError, match="no_such_old_module"):
        importlib.import_module("mitsuba_powder.no_such_old_module")
