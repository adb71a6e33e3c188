"""Shared helpers of the benchmark scripts: timing, machine description, result files."""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import time
from pathlib import Path

import drjit as dr
import numpy as np

OUT = Path(__file__).resolve().parent / "results"


def arg_parser(doc: str) -> argparse.ArgumentParser:
    """The options every benchmark script has: ``--quick`` (CI sizes) and ``--out``."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes (CI)")
    parser.add_argument("--out", type=Path, default=OUT, help="folder for .json and .png")
    return parser


def throughput_sizes(quick: bool, pairs: int, repeat: int) -> tuple[int, int, int]:
    """(direction pairs per JIT call, Python-level calls of a scalar variant, repeats) of a
    BSDF throughput run: ``pairs`` and ``repeat`` at full size, tiny ones with ``quick``."""
    return (1024, 200, 2) if quick else (pairs, 20_000, repeat)


def use_variant(variant: str) -> None:
    """Select a Mitsuba variant (it stays selected) and make the powder plugin findable in it
    (:func:`mitsuba_powder.variants.set_variant`)."""
    from mitsuba_powder.variants import set_variant

    set_variant(variant)


def barh_figure(path: Path, labels, values, colors, xlabel: str, log: bool = False,
                figsize=(7, 3.5)) -> None:
    """A horizontal bar chart, first label on top, written to ``path``."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=figsize)
    ax.barh(labels, values, color=colors)
    if log:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.invert_yaxis()
    ax.tick_params(labelsize=7)
    save_figure(fig, path)


def save_figure(fig, path: Path, dpi: int = 100) -> None:
    """Lay out ``fig`` (a pyplot figure), write it to ``path`` and close it."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)


def timeit(fn, repeat: int, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` in seconds after ``warmup`` calls (kernel compilation).
    Dr.Jit launches kernels asynchronously: the clock stops after ``dr.sync_thread()``."""
    for _ in range(warmup):
        fn()
        dr.sync_thread()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        dr.sync_thread()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def wall_seconds(call) -> float:
    """Wall time of ``dr.eval(call())`` in seconds, the clock stopped after
    ``dr.sync_thread()`` (Dr.Jit launches kernels asynchronously)."""
    t = time.perf_counter()
    dr.eval(call())
    dr.sync_thread()
    return time.perf_counter() - t


def kernel_seconds(call) -> float:
    """Execution time in seconds of the kernels that ``dr.eval(call())`` launches (Dr.Jit's
    kernel history: no tracing, no Python)."""
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.eval(call())
        dr.sync_thread()
        history = dr.kernel_history()
    return 1e-3 * float(sum(e["execution_time"] for e in history
                            if e["type"] == dr.KernelType.JIT))


def cpu_seconds(call) -> float:
    """Processor time in seconds of ``dr.eval(call())`` (every thread of this process: the
    caller and Dr.Jit's pool). On cores shared with other processes it does not count the
    time they hold the cores, which wall times do; with one Dr.Jit thread
    (``dr.set_thread_count(1)``) it is the single-thread cost of the call, tracing included."""
    t = time.process_time()
    dr.eval(call())
    dr.sync_thread()
    return time.process_time() - t


def eval_calls(bsdfs: dict, ctx, si, wo) -> dict:
    """{label: a function that evaluates that BSDF's ``eval`` at (si, wo)}, for time_in_turn."""
    return {label: functools.partial(bsdf.eval, ctx, si, wo) for label, bsdf in bsdfs.items()}


def time_in_turn(calls: dict, repeat: int, clock=wall_seconds) -> dict[str, np.ndarray]:
    """Seconds of each of ``calls`` (label: function returning Dr.Jit values), timed in turn
    within each of ``repeat`` rounds after one warm-up call each (kernel compilation), so that
    a change of machine load hits them alike; ``clock`` times one call (wall_seconds,
    kernel_seconds or cpu_seconds)."""
    for call in calls.values():
        clock(call)
    times: dict[str, list[float]] = {k: [] for k in calls}
    for _ in range(repeat):
        for label, call in calls.items():
            times[label].append(clock(call))
    return {k: np.array(v) for k, v in times.items()}


def machine() -> dict:
    """What the numbers were measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import mitsuba as mi

    return {"cpu": cpu, "cpus": os.cpu_count(), "python": platform.python_version(),
            "mitsuba": mi.__version__, "drjit": dr.__version__,
            "date": time.strftime("%Y-%m-%d")}


def save(out: Path, name: str, rows: list[dict], quick: bool, **extra) -> Path:
    """Write ``out/name.json`` with the machine, the mode and the raw rows."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.json"
    path.write_text(json.dumps({"meta": {**machine(), "quick": quick, **extra}, "rows": rows},
                               indent=1))
    return path


def pyplot():
    """matplotlib.pyplot with a non-interactive backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def print_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> None:
    """Print ``rows`` as a fixed-width table; ``columns`` = (key, header, format)."""
    widths = [max(len(h), 10) for _, h, _ in columns]
    print("  ".join(f"{h:>{w}s}" for (_, h, _), w in zip(columns, widths, strict=True)))
    for r in rows:
        cells = []
        for (key, _, fmt), w in zip(columns, widths, strict=True):
            v = r.get(key)
            cells.append(f"{'-' if v is None else format(v, fmt):>{w}s}")
        print("  ".join(cells))


def random_pairs(n: int, variant: str, seed: int = 0, sorted_wavelengths: bool = False):
    """``n`` random direction pairs on the upper hemisphere (cosines in [0.1, 1]) as
    ``(si, wo)`` of the current Mitsuba variant; in spectral variants each lane gets four
    random wavelengths in 360-830 nm. ``sorted_wavelengths``: the same wavelengths, each
    channel's sorted across the lanes (the same values and the same work per lane; neighbouring
    lanes then read neighbouring records of a per-wavelength table)."""
    import mitsuba as mi

    rng = np.random.default_rng(seed)
    mu = rng.uniform(0.1, 1, (2, n))
    phi = rng.uniform(0, 2 * np.pi, (2, n))
    s = np.sqrt(1 - mu**2)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(s[0] * np.cos(phi[0]), s[0] * np.sin(phi[0]), mu[0])
    if "spectral" in variant:
        lam = rng.uniform(360, 830, (4, n))
        si.wavelengths = mi.UnpolarizedSpectrum(*(np.sort(lam, axis=1) if sorted_wavelengths
                                                  else lam))
    wo = mi.Vector3f(s[1] * np.cos(phi[1]), s[1] * np.sin(phi[1]), mu[1])
    return si, wo
