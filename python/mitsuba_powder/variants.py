"""Select Mitsuba variants: the one helper the package, its tests and benchmarks switch with.

Mitsuba's variant is process-wide state (``mi.set_variant``), and a library function that
changes it behind its caller's back breaks the caller's next ``mi.load_dict``. So the package
switches only through :func:`use_variant`, which restores the caller's variant on exit;
:func:`set_variant` is the plain form for scripts and tests that want the variant to stay.

Both check the name against ``mi.variants()`` and the backend it needs (a CUDA device for
``cuda_*``, a usable LLVM for ``llvm_*``) and make the ``powder`` plugin findable in it
(:func:`mitsuba_powder.register`).

Mitsuba cannot unset a variant: when none was selected before :func:`use_variant`, the block's
variant stays selected after it.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import drjit as dr
import mitsuba as mi

__all__ = ["check_variant", "set_variant", "use_variant"]


def check_variant(name: str) -> None:
    """Raise unless ``name`` is a variant of this Mitsuba build whose backend can run here.

    Raises:
        ValueError: ``name`` is not one of ``mi.variants()`` (the message lists them).
        RuntimeError: a ``cuda_*`` variant without a CUDA device, or an ``llvm_*`` variant
            without a usable LLVM backend (see :func:`mitsuba_powder.check_llvm`).
    """
    if not isinstance(name, str) or name not in mi.variants():
        raise ValueError(f"variant = {name!r} is not available in this Mitsuba build; choose "
                         f"one of {', '.join(mi.variants())}")
    if name.startswith("cuda_") and not dr.has_backend(dr.JitBackend.CUDA):
        raise RuntimeError(f"variant = {name!r} needs a CUDA device and Dr.Jit found none "
                           "here; use an llvm_* or scalar_* variant")
    if name.startswith("llvm_"):
        from ._llvm import check_llvm

        status = check_llvm()
        if not dr.has_backend(dr.JitBackend.LLVM) or not status.usable:
            raise RuntimeError(f"variant = {name!r} needs Dr.Jit's LLVM backend, which is not "
                               f"usable here: {status.message or 'no libLLVM found'}; use a "
                               "scalar_* variant")


def set_variant(name: str) -> str | None:
    """Select the Mitsuba variant ``name`` (it stays selected) and register the plugin.

    Args:
        name: a variant of ``mi.variants()``, e.g. ``scalar_rgb`` or ``llvm_ad_mono``.

    Returns:
        The variant selected before the call (``None`` when there was none).

    Raises:
        ValueError, RuntimeError: see :func:`check_variant`.
    """
    previous = mi.variant()
    if previous != name:
        check_variant(name)
        mi.set_variant(name)
    from . import register

    register()
    return previous


@contextmanager
def use_variant(name: str) -> Iterator[str]:
    """Use the Mitsuba variant ``name`` inside a ``with`` block, then restore the caller's.

    Free when ``name`` is already selected (nested use, e.g. once per objective evaluation);
    otherwise the variant is checked, selected and the plugin registered as by
    :func:`set_variant`. On exit (normal or by an exception) the variant selected before the
    block is selected again, even if the block switched variants itself.

    Args:
        name: a variant of ``mi.variants()``.

    Yields:
        ``name``.

    Raises:
        ValueError, RuntimeError: see :func:`check_variant` (raised before the block runs).
    """
    previous = mi.variant()
    if previous != name:
        set_variant(name)
    try:
        yield name
    finally:
        if previous is not None and mi.variant() != previous:
            mi.set_variant(previous)
