"""Detect a Dr.Jit LLVM backend that would abort the process.

Dr.Jit 1.5 picks the newest ``libLLVM`` it finds. Debian 12 ships libLLVM 15 by default,
which cannot lower the ``fmaximum`` intrinsic: the first LLVM kernel that uses
``dr.maximum`` aborts the whole Python process ("Cannot select"). LLVM 19 (Debian package
``libllvm19``) works. This module finds out before that happens.
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

#: Oldest LLVM major version verified to work with drjit 1.5.0 (older ones are probed).
VERIFIED_LLVM_MAJOR = 19

FIX = (
    "install LLVM 19 ('apt-get install libllvm19' on Debian/Ubuntu) or point Dr.Jit at a "
    "working libLLVM with the environment variable DRJIT_LIBLLVM_PATH"
)

_PROBE = (
    "import drjit as dr\n"
    "from drjit.llvm import Float\n"
    "x = dr.maximum(Float(1.0, 2.0), 1.5)\n"
    "dr.eval(x)\n"
    "assert list(x) == [1.5, 2.0]\n"
)


@dataclass(frozen=True)
class LLVMStatus:
    """Outcome of :func:`check_llvm`.

    Attributes:
        version: (major, minor, patch) of the libLLVM Dr.Jit loaded; (-1, -1, -1) if none.
        usable: True if LLVM variants can run kernels in this process.
        message: human-readable explanation (empty when usable).
    """

    version: tuple[int, int, int]
    usable: bool
    message: str


_cached: LLVMStatus | None = None


def _probe_in_subprocess() -> bool:
    """Run a small LLVM kernel in a child process (an abort there cannot kill us)."""
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE],
            capture_output=True,
            timeout=120,
            env=dict(os.environ),
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return proc.returncode == 0


def check_llvm(on_import: bool = False) -> LLVMStatus:
    """Check that Dr.Jit's LLVM backend works, without risking this process.

    LLVM versions >= :data:`VERIFIED_LLVM_MAJOR` are accepted without a probe; older
    ones are tested by running one kernel in a subprocess.

    Args:
        on_import: when True (as on ``import mitsuba_powder``), a broken LLVM raises
            ``RuntimeError`` if the current Mitsuba variant is an LLVM one and only warns
            otherwise (scalar and CUDA variants still work).

    Returns:
        The :class:`LLVMStatus`.
    """
    global _cached
    if _cached is None:
        version = tuple(int(v) for v in dr.detail.llvm_version())
        if version[0] < 0:
            status = LLVMStatus(version, False, "Dr.Jit found no libLLVM: " + FIX)
        elif version[0] >= VERIFIED_LLVM_MAJOR or _probe_in_subprocess():
            status = LLVMStatus(version, True, "")
        else:
            status = LLVMStatus(
                version,
                False,
                f"Dr.Jit's LLVM backend uses libLLVM {version[0]}.{version[1]}, which aborts "
                f"the process on the first kernel ('Cannot select'): {FIX}",
            )
        _cached = status
    status = _cached
    if on_import and not status.usable:
        variant = mi.variant() or ""
        if variant.startswith("llvm_"):
            raise RuntimeError("mitsuba_powder: " + status.message)
        warnings.warn(
            "mitsuba_powder: llvm_* variants are unusable: " + status.message,
            RuntimeWarning,
            stacklevel=3,
        )
    return status
