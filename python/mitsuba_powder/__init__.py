"""mitsuba-powder: the dry-powder BSDF of Gerardin, Martinetto and Holzschuch (2023) for Mitsuba 3.

Importing this package makes the ``powder`` plugin findable by Mitsuba: it prepends the
package folder (which holds ``plugins/powder.so``) to Mitsuba's file resolver, so that
``mi.load_dict({'type': 'powder', ...})`` and ``<bsdf type="powder">`` work in every variant.

It first checks that the imported mitsuba and drjit are the releases the plugin was compiled
against (:mod:`._versions`: ``ImportError`` otherwise, with the command that rebuilds it). It
also checks that Dr.Jit's LLVM backend is usable (Debian 12's default libLLVM 15 makes
it abort the process on the first kernel); see :func:`check_llvm`, and keeps the module names
from before the sub-packages importable, with a deprecation warning (:mod:`._compat`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import drjit as dr
import mitsuba as mi

from . import _compat
from ._llvm import LLVMStatus, check_llvm
from ._versions import built_for, check_versions

__all__ = ["plugin_dir", "plugin_path", "register", "check_llvm", "LLVMStatus", "__version__"]
__version__ = built_for()["mitsuba-powder"]  # pyproject.toml's, recorded by the build

_PACKAGE_DIR = Path(__file__).resolve().parent


def plugin_dir() -> Path:
    """Folder to give Mitsuba's file resolver (or ``mitsuba -a``): it contains ``plugins/``."""
    return _PACKAGE_DIR


def plugin_path() -> Path:
    """Path of the compiled plugin library: ``plugins/powder.so`` (``.dylib`` on macOS,
    ``.dll`` on Windows, the names Mitsuba's plugin manager looks for)."""
    suffix = {"win32": ".dll", "darwin": ".dylib"}.get(sys.platform, ".so")
    return _PACKAGE_DIR / "plugins" / f"powder{suffix}"


def register() -> None:
    """Prepend :func:`plugin_dir` to Mitsuba's file resolver of the calling thread.

    Called on import. Call it again in a thread that Mitsuba did not create from the
    importing thread before loading a scene there.

    Raises:
        FileNotFoundError: the plugin library is missing (the package was not built).
    """
    if not plugin_path().is_file():
        raise FileNotFoundError(
            f"mitsuba_powder: the compiled plugin {plugin_path()} is missing; "
            "reinstall the package with 'pip install .' so that it is built"
        )
    resolver = mi.file_resolver()
    folder = str(_PACKAGE_DIR)
    if folder not in [str(p) for p in resolver]:
        resolver.prepend(folder)


check_versions(mi.__version__, dr.__version__)  # before anything loads the plugin
_compat.install()
register()
check_llvm(on_import=True)
