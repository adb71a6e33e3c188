"""The package's dependencies, with mitsuba and drjit pinned to the build environment's.

A scikit-build-core metadata provider (pyproject.toml, ``[tool.scikit-build.metadata.
dependencies]``): the C++ plugin loads only into the mitsuba and drjit releases it was compiled
against, so the wheel requires exactly those. With build isolation they are the ones
``build-system.requires`` pins; with ``--no-build-isolation`` the environment's own (any release
of the supported range that CMakeLists.txt checks), so that installing the package never
replaces the mitsuba it was built for.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

#: the distributions whose versions are pinned, in the order written
PINNED = ("mitsuba", "drjit")


def pins() -> list[str]:
    """``["mitsuba==X", "drjit==Y"]`` for the distributions installed in this environment.

    Raises:
        RuntimeError: one of them is not installed (a ``--no-build-isolation`` build in an
            environment without mitsuba).
    """
    out = []
    for name in PINNED:
        try:
            out.append(f"{name}=={version(name)}")
        except PackageNotFoundError:
            raise RuntimeError(
                f"mitsuba-powder is built against the installed {name}, and the build "
                f"environment has none: install mitsuba (with its drjit) before building with "
                "--no-build-isolation (docs/install.md)") from None
    return out


def dynamic_metadata(field: str, settings: dict) -> list[str]:
    """scikit-build-core's provider hook: ``settings["requires"]`` plus :func:`pins`."""
    if field != "dependencies":
        raise RuntimeError(f"powder_pins provides 'dependencies', not {field!r}")
    requires = settings.get("requires", [])
    if not isinstance(requires, list) or not all(isinstance(r, str) for r in requires):
        raise RuntimeError("powder_pins: 'requires' must be a list of requirement strings")
    return pins() + list(requires)
