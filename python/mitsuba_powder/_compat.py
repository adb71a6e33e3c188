"""The old flat module names (``mitsuba_powder.fit``, ``mitsuba_powder.model``, ...), importable
for one release after the modules moved into sub-packages.

:data:`MOVED` maps each old module name to the module that now holds its contents. A finder at
the end of ``sys.meta_path`` answers ``import mitsuba_powder.<old>`` with the new module object
itself (``sys.modules`` then holds it under both names, so ``mitsuba_powder.fit.fit is
mitsuba_powder.fitting.fit.fit``) and emits a :class:`DeprecationWarning` that names the new
module. Being last, the finder never shadows a module file that still exists under its old name;
an entry whose new module does not exist is inactive (the import fails as it would without it).
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import warnings
from types import ModuleType

#: old module name -> new module name
MOVED: dict[str, str] = {
    "mitsuba_powder.params": "mitsuba_powder.plugin.params",
    "mitsuba_powder.grain_optics": "mitsuba_powder.plugin.grains",
    "mitsuba_powder.model": "mitsuba_powder.plugin.brf",
    "mitsuba_powder.appearance": "mitsuba_powder.plugin.appearance",
    "mitsuba_powder.measurements": "mitsuba_powder.io.measurements",
    "mitsuba_powder.ipag": "mitsuba_powder.io.ipag",
    "mitsuba_powder.ptfe": "mitsuba_powder.io.ptfe",
    "mitsuba_powder.optimise": "mitsuba_powder.fitting.optimise",
    "mitsuba_powder.fit": "mitsuba_powder.fitting.fit",
    "mitsuba_powder.fit_report": "mitsuba_powder.fitting.report",
    "mitsuba_powder.baselines": "mitsuba_powder.fitting.baselines",
    "mitsuba_powder.model_comparison": "mitsuba_powder.fitting.comparison",
    "mitsuba_powder.protocols": "mitsuba_powder.fitting.protocols",
    "mitsuba_powder.render": "mitsuba_powder.rendering.render",
    "mitsuba_powder.scene_description": "mitsuba_powder.rendering.scene_description",
    "mitsuba_powder.gonio": "mitsuba_powder.rendering.gonio",
    "mitsuba_powder.gonio_report": "mitsuba_powder.rendering.gonio_report",
    "mitsuba_powder.furnace": "mitsuba_powder.rendering.furnace",
    "mitsuba_powder.photo_comparison": "mitsuba_powder.rendering.photo",
    "mitsuba_powder.rti_fit": "mitsuba_powder.rti",
    "mitsuba_powder.rti_maps": "mitsuba_powder.rti.maps",
    "mitsuba_powder.rti_baselines": "mitsuba_powder.rti.baselines",
    "mitsuba_powder.rti_compare": "mitsuba_powder.rti.comparison",
}


def _exists(name: str) -> bool:
    """Whether module ``name`` can be found (its parent packages are imported to look)."""
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):  # a parent is missing or is not a package
        return False


class _AliasLoader(importlib.abc.Loader):
    """Loads an old name as the new module object, with a deprecation warning."""

    def __init__(self, new: str) -> None:
        self.new = new
        self._spec: importlib.machinery.ModuleSpec | None = None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        warnings.warn(f"{spec.name} is deprecated and will be removed; import {self.new} "
                      "instead", DeprecationWarning, stacklevel=2)
        module = importlib.import_module(self.new)
        self._spec = module.__spec__
        return module

    def exec_module(self, module: ModuleType) -> None:
        # the import system set the alias's spec on the shared module object: give it back its
        # own, so that the module keeps its one true name
        module.__spec__ = self._spec


class _AliasFinder(importlib.abc.MetaPathFinder):
    """Finds the old module names of :data:`MOVED` whose new module exists."""

    def find_spec(self, fullname: str, path=None, target=None
                  ) -> importlib.machinery.ModuleSpec | None:
        new = MOVED.get(fullname)
        if new is None or not _exists(new):
            return None
        return importlib.machinery.ModuleSpec(fullname, _AliasLoader(new))


def install() -> None:
    """Append the finder to ``sys.meta_path`` (once)."""
    if not any(isinstance(f, _AliasFinder) for f in sys.meta_path):
        sys.meta_path.append(_AliasFinder())
