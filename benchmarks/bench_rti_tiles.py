"""Benchmark of the tiled per-pixel fit :func:`mitsuba_powder.rti.tiles.fit_maps_tiled` on a
SYNTHETIC capture on disk, through a local Dask cluster of worker processes: wall time, peak
memory per worker, and a run in which a worker is killed half-way.

    python benchmarks/bench_rti_tiles.py [--quick] [--size 2048] [--lights 50]
        [--tile-size 512] [--workers 2] [--work DIR] [--variant llvm_ad_rgb]

The capture is the one of ``rti.synthetic_capture(size, size, lights, noise=0.01)`` (four
quadrants, a gentle relief, lights on a 10-80 degree dome, exposure 2, all gains 1), written
as linear half-float EXR images (``bit_depth=16``) and an ``.lp`` file into a temporary
folder (or ``--work DIR``, kept; a capture of the same size, lights and noise already there
is used again). It is rendered in groups of consecutive lights
(:func:`~mitsuba_powder.rti.render_capture` on the whole image, at most 128 MiB of float32
images per group) and each group is written before the next is rendered, with the noise
drawn from the same stream as ``synthetic_capture``'s: the images are those of
``synthetic_capture`` (checked, bit for bit, where that is cheap: ``--quick``), but this
process holds the maps, one group and its float64 noise and sum at a time (about 1 GiB in
all at 2048^2, estimated) instead of the whole (K, H, W, 3) stack, clean and noisy, with its
float64 temporaries (about 12 GiB at 2048^2 x 50).

Two fits, each on a fresh ``distributed.LocalCluster`` of ``--workers`` processes with one
thread each (``processes=True``, the settings of :func:`mitsuba_powder.rti.cluster.open_client`;
each tile then runs Dr.Jit on two threads, the minimum the fit allows), ``encoding="linear"``,
``gains="fit"`` (on at most 16384 pixels) and the default fit options:

* ``uninterrupted``: :func:`fit_maps_tiled` into ``run1/``;
* ``worker killed``: the same into ``run2/``; once half of the tiles are written (``on_tile``)
  a busy worker is killed with SIGKILL, its nanny starts a new one and Dask fits the lost
  tile(s) again; had the run stopped with an error, it would be resumed (``resume=True``).
  Its maps are compared with run 1's, bit for bit (every map, NaN-aware): ``identical``.

Before them an untimed warm-up fit (a block of at most 64 x 64 px of the first tile, by a
mask, on a cluster of its own; ``--no-warmup``: none) fills Dr.Jit's kernel cache on disk, so
that run 1 does not pay for compiling kernels that run 2 then finds cached. Wall times are of
the :func:`fit_maps_tiled` calls (cluster start not included: ``start_s`` in the JSON);
peak memory is each worker process's ``ru_maxrss`` at the end of its run (the killed worker's
just before it was killed, its replacement's at the end) and this process's own. Prints a
table (``fitted``/``resumed``: tiles of the last :func:`fit_maps_tiled` call of the run;
``lost``: tiles the killed worker held) and writes ``rti_tiles.json`` and ``rti_tiles.png``
into ``--out``.

Default: 2048 x 2048 px (4 MP) x 50 lights, tiles of 512 px (16 tiles), two workers.
``--quick`` (CI): 64 x 64 px x 12 lights, tiles of 32 px (4 tiles).
"""

from __future__ import annotations

import json
import logging
import os
import resource
import shutil
import signal
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from _common import arg_parser, print_table, pyplot, save, save_figure

#: noise of the synthetic capture, linear units (1 = full scale)
NOISE = 0.01
#: exposure of :func:`synthetic_capture` (its default): the lights' irradiance
EXPOSURE = 2.0
#: float32 images rendered at once, MiB (the group's float64 noise and sum come on top)
RENDER_GROUP_MIB = 128
#: bits per component of the EXR images (16: half float)
BIT_DEPTH = 16
#: sizes of ``--quick``: (size px, lights, tile size px)
QUICK = (64, 12, 32)
#: seconds to wait for the killed worker's replacement
WORKER_TIMEOUT = 120


# ---------------------------------------------------------------------------
#  The capture
# ---------------------------------------------------------------------------

def _light_groups(size: int, lights: int) -> list[slice]:
    """Consecutive lights rendered together: at most :data:`RENDER_GROUP_MIB` MiB of float32
    (size, size, 3) images per group (at least one light)."""
    per_light = size * size * 3 * 4
    n = max(1, (RENDER_GROUP_MIB << 20) // per_light)
    return [slice(k, min(k + n, lights)) for k in range(0, lights, n)]


def render_capture_files(folder: Path, size: int, lights: int, variant: str) -> Path:
    """Render ``synthetic_capture(size, size, lights, noise=NOISE)`` group of lights by group
    of lights (module docstring) and write it to ``folder`` as half-float EXR images and
    ``capture.lp``; returns the ``.lp`` path."""
    from mitsuba_powder import rti

    maps, _ = rti.synthetic_maps(size, size)
    directions = rti.dome_directions(lights)
    gains = EXPOSURE * np.ones(lights)
    names = [f"light{k:03d}.exr" for k in range(lights)]
    rng = np.random.default_rng(1)  # synthetic_capture's noise: seed + 1, in (K, H, W, 3) order
    folder.mkdir(parents=True, exist_ok=True)
    for group in _light_groups(size, lights):
        clean = rti.render_capture(maps, directions[group], gains[group], variant)
        images = (clean + rng.normal(0.0, NOISE, clean.shape)).astype(np.float32)
        del clean
        like = rti.Capture(images=images, directions=directions[group], names=names[group],
                           encoding="linear", file_format="exr", bit_depth=BIT_DEPTH)
        rti.write_images(like, images, names[group], folder)
        del images
    return rti.write_lp(folder / "capture.lp", names, directions)


def same_as_synthetic_capture(size: int, lights: int, variant: str) -> bool:
    """Whether the grouped rendering gives ``synthetic_capture``'s images bit for bit (both
    in memory, float32, before the EXR's rounding to half floats)."""
    from mitsuba_powder import rti

    whole = rti.synthetic_capture(size, size, lights, noise=NOISE, variant=variant)["images"]
    maps, _ = rti.synthetic_maps(size, size)
    directions = rti.dome_directions(lights)
    rng = np.random.default_rng(1)
    parts = []
    for group in _light_groups(size, lights):
        clean = rti.render_capture(maps, directions[group], EXPOSURE * np.ones(lights)[group],
                                   variant)
        parts.append((clean + rng.normal(0.0, NOISE, clean.shape)).astype(np.float32))
    return bool(np.array_equal(np.concatenate(parts), whole))


def capture_lp(work: Path, size: int, lights: int, variant: str) -> tuple[Path, float, bool]:
    """The capture's ``.lp`` in ``work/capture``: rendered and written, or reused when
    ``capture.json`` there says the same size, lights, noise, bit depth and variant.

    Returns:
        (.lp path, seconds spent rendering and writing (0 if reused), reused)."""
    folder = work / "capture"
    spec = {"size": size, "lights": lights, "noise": NOISE, "exposure": EXPOSURE,
            "bit_depth": BIT_DEPTH, "variant": variant}
    record = folder / "capture.json"
    lp = folder / "capture.lp"
    if lp.is_file() and record.is_file() and json.loads(record.read_text()) == spec:
        return lp, 0.0, True
    if folder.exists():
        shutil.rmtree(folder)
    t0 = time.perf_counter()
    lp = render_capture_files(folder, size, lights, variant)
    record.write_text(json.dumps(spec))
    return lp, time.perf_counter() - t0, False


# ---------------------------------------------------------------------------
#  Memory, cluster
# ---------------------------------------------------------------------------

def peak_rss_mib() -> float:
    """Peak resident memory of the calling process, MiB (``ru_maxrss``: KiB on Linux); run on
    the workers with ``client.run``."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def worker_pid() -> int:
    """The calling (worker) process's id."""
    return os.getpid()


def local_cluster(workers: int):
    """A local cluster of ``workers`` processes with one thread each and a client of it, the
    settings of :func:`mitsuba_powder.rti.cluster.open_client` (to be closed by the caller)."""
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address=":0", silence_logs=logging.ERROR)
    return cluster, Client(cluster)


def _worker_peaks(client) -> list[float]:
    """Each worker's peak resident memory, MiB, in the order of the workers' addresses."""
    peaks = client.run(peak_rss_mib)
    return [round(peaks[a], 1) for a in sorted(peaks)]


# ---------------------------------------------------------------------------
#  The runs
# ---------------------------------------------------------------------------

def _fit(lp: Path, out: Path, tile_size: int, client, variant: str,
         on_tile: Callable[[str, int, int], None] | None = None, resume: bool = False):
    """One :func:`fit_maps_tiled` call of the benchmark's settings."""
    from mitsuba_powder.rti.tiles import fit_maps_tiled

    return fit_maps_tiled(lp, out, tile_size, encoding="linear", gains="fit", client=client,
                          resume=resume, progress=False, on_tile=on_tile, variant=variant,
                          log=lambda line: print(f"    {line}", flush=True))


def warm_up(lp: Path, out: Path, size: int, tile_size: int, workers: int, variant: str
            ) -> float:
    """An untimed fit of a block of at most 64 x 64 px (a mask) in the first tile, on a
    cluster of its own, so that Dr.Jit's kernel cache on disk holds the fit's kernels before
    run 1 as before run 2; returns its seconds (cluster included)."""
    t0 = time.perf_counter()
    block = min(64, tile_size, size)
    mask = np.zeros((size, size), bool)
    mask[:block, :block] = True
    cluster, client = local_cluster(workers)
    try:
        from mitsuba_powder.rti.tiles import fit_maps_tiled

        fit_maps_tiled(lp, out, tile_size, encoding="linear", gains="fit", client=client,
                       mask=mask, progress=False, variant=variant)
    finally:
        client.close()
        cluster.close()
    return time.perf_counter() - t0


def _tile_row(result, seconds: float) -> dict:
    """The row's entries taken from a fit's result."""
    tiles = result.fit_settings["tiles"]
    return {"fit_s": round(seconds, 2), "tiles": tiles["count"], "fitted": tiles["fitted"],
            "resumed": tiles["resumed"]}


def run_uninterrupted(lp: Path, out: Path, tile_size: int, workers: int, variant: str
                      ) -> tuple[dict, object]:
    """Run 1: the fit on a fresh cluster, uninterrupted. Returns (row, result)."""
    t0 = time.perf_counter()
    cluster, client = local_cluster(workers)
    try:
        start_s = time.perf_counter() - t0
        stamps: list[float] = []
        t1 = time.perf_counter()
        result = _fit(lp, out, tile_size, client, variant,
                      on_tile=lambda name, done, total: stamps.append(time.perf_counter() - t1))
        seconds = time.perf_counter() - t1
        peaks = _worker_peaks(client)
    finally:
        client.close()
        cluster.close()
    row = _run_row("uninterrupted", start_s, result, seconds, stamps, peaks,
                   killed_at_s=None, tiles_lost=None, resume_s=None, aborted=None)
    return row, result


def run_killed(lp: Path, out: Path, tile_size: int, workers: int, variant: str
               ) -> tuple[dict, object]:
    """Run 2: the fit on a fresh cluster, a busy worker killed (SIGKILL) once half of the
    tiles are written; resumed with ``resume=True`` if the run stops with an error.
    Returns (row, result)."""
    t0 = time.perf_counter()
    cluster, client = local_cluster(workers)
    kill: dict = {}
    stamps: list[float] = []
    try:
        start_s = time.perf_counter() - t0
        t1 = time.perf_counter()

        def on_tile(name: str, done: int, total: int) -> None:
            stamps.append(time.perf_counter() - t1)
            if kill or done < max(1, total // 2) or done >= total:
                return
            processing = client.processing()
            busy = sorted(a for a, keys in processing.items() if keys)
            pids = client.run(worker_pid)
            victim = (busy or sorted(pids))[0]
            peak = client.run(peak_rss_mib, workers=[victim])[victim]
            os.kill(pids[victim], signal.SIGKILL)
            kill.update(at_s=time.perf_counter() - t1, after_tiles=done, worker=victim,
                        tiles_lost=len(processing.get(victim, ())), peak_mib=round(peak, 1))
            print(f"    killed worker {victim} (pid {pids[victim]}) after {done} of {total} "
                  f"tiles, {kill['at_s']:.1f} s; it was fitting {kill['tiles_lost']} tile(s)",
                  flush=True)

        aborted = None
        resume_s = None
        try:
            result = _fit(lp, out, tile_size, client, variant, on_tile=on_tile)
            seconds = time.perf_counter() - t1
        except Exception as exc:  # the run stopped: resume it
            aborted = f"{type(exc).__name__}: {exc}"
            print(f"    the run stopped ({aborted}); resuming", flush=True)
            client.wait_for_workers(workers, timeout=WORKER_TIMEOUT)
            t2 = time.perf_counter()
            result = _fit(lp, out, tile_size, client, variant, resume=True)
            resume_s = round(time.perf_counter() - t2, 2)
            seconds = time.perf_counter() - t1
        client.wait_for_workers(workers, timeout=WORKER_TIMEOUT)  # the killed one's replacement
        peaks = _worker_peaks(client)
    finally:
        client.close()
        cluster.close()
    row = _run_row("worker killed", start_s, result, seconds, stamps, peaks,
                   killed_at_s=round(kill["at_s"], 2) if kill else None,
                   killed_after_tiles=kill.get("after_tiles"),
                   tiles_lost=kill.get("tiles_lost"),
                   killed_worker_peak_mib=kill.get("peak_mib"), resume_s=resume_s,
                   aborted=aborted)
    return row, result


def _run_row(run: str, start_s: float, result, seconds: float, stamps: list[float],
             peaks: list[float], **extra) -> dict:
    """A run's row: its name, the cluster's start (s), the tiles' numbers, the fit's wall
    time (s), when each tile finished (s), the workers' peaks (MiB), and ``extra``."""
    return {"run": run, "start_s": round(start_s, 2), **_tile_row(result, seconds),
            "first_tile_s": round(stamps[0], 2) if stamps else None,
            "tile_times_s": [round(t, 2) for t in stamps], "peak_mib_workers": peaks, **extra}


def identical(a, b) -> dict[str, bool]:
    """Bit-for-bit equality of two results' arrays (NaN equal to NaN), by name."""
    fields = {"normals": (a.normals, b.normals), "albedo": (a.albedo, b.albedo),
              "residual_rms": (a.residual_rms, b.residual_rms), "used": (a.used, b.used),
              "mask": (a.mask, b.mask), "gains": (a.gains, b.gains)}
    for name in sorted(set(a.maps) | set(b.maps)):
        fields[f"maps[{name}]"] = (a.maps.get(name), b.maps.get(name))
    out = {}
    for name, (x, y) in fields.items():
        if x is None or y is None:
            out[name] = False
            continue
        x, y = np.asarray(x), np.asarray(y)
        nan_ok = np.issubdtype(x.dtype, np.floating)
        out[name] = bool(x.shape == y.shape and x.dtype == y.dtype
                         and np.array_equal(x, y, equal_nan=nan_ok))
    return out


# ---------------------------------------------------------------------------
#  Output
# ---------------------------------------------------------------------------

def _figure(path: Path, rows: list[dict]) -> None:
    """The runs' wall times as horizontal bars; the kill (and a resume) marked on run 2's."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 2.6))
    labels = [r["run"] for r in rows]
    ax.barh(labels, [r["fit_s"] for r in rows], color=["tab:blue", "tab:orange"][:len(rows)])
    for i, r in enumerate(rows):
        if r.get("killed_at_s") is not None:
            ax.plot([r["killed_at_s"]] * 2, [i - 0.4, i + 0.4], color="tab:red", lw=2)
            ax.annotate("worker killed", (r["killed_at_s"], i + 0.42), color="tab:red",
                        fontsize=7, ha="center", va="top")
        ax.annotate(f"{r['fit_s']:.1f} s", (r["fit_s"], i), fontsize=7, ha="left",
                    va="center", xytext=(3, 0), textcoords="offset points")
    ax.set_xlabel("fit_maps_tiled wall time (s)")
    ax.set_xlim(0, 1.15 * max(r["fit_s"] for r in rows))
    ax.invert_yaxis()
    ax.set_title(rows[0]["capture"], fontsize=8)
    save_figure(fig, path)


COLUMNS = [("run", "run", "s"), ("capture", "capture", "s"), ("tiles", "tiles", "d"),
           ("workers", "workers", "d"), ("fit_s", "fit s", ".1f"),
           ("peak_text", "peak MiB/worker", "s"), ("fitted", "fitted", "d"),
           ("resumed", "resumed", "d"), ("tiles_lost", "lost", "d"),
           ("identical_text", "identical", "s")]


def main() -> None:
    ap = arg_parser(__doc__)
    ap.add_argument("--size", type=int, default=2048, help="image side, px (default 2048)")
    ap.add_argument("--lights", type=int, default=50, help="lights (default 50)")
    ap.add_argument("--tile-size", type=int, default=512, help="tile side, px (default 512)")
    ap.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--work", type=Path, default=None,
                    help="folder for the capture and the runs' outputs, kept (its capture/ "
                         "is reused when it matches; warmup/, run1/ and run2/ are replaced); "
                         "default: a temporary folder, removed")
    ap.add_argument("--no-warmup", action="store_true",
                    help="no untimed warm-up fit before run 1 (Dr.Jit's kernel cache cold)")
    args = ap.parse_args()
    size, lights, tile = QUICK if args.quick else (args.size, args.lights, args.tile_size)
    capture = f"{size} x {size} x {lights}"
    print(f"SYNTHETIC capture {capture} lights, half-float EXR; tiles of {tile} px; "
          f"{args.workers} workers x 1 thread", flush=True)
    with tempfile.TemporaryDirectory(prefix="bench_rti_tiles_") as tmp:
        work = Path(tmp) if args.work is None else args.work
        work.mkdir(parents=True, exist_ok=True)
        lp, render_s, reused = capture_lp(work, size, lights, args.variant)
        render_peak = peak_rss_mib()
        print(f"  capture {'reused' if reused else f'rendered and written in {render_s:.1f} s'}"
              f": {lp} ({sum(p.stat().st_size for p in lp.parent.glob('*.exr')) / 2**20:.1f} "
              f"MiB of EXR)", flush=True)
        check = (same_as_synthetic_capture(size, lights, args.variant)
                 if size * size * lights <= 1 << 18 else None)
        warm_s = None
        if not args.no_warmup:
            shutil.rmtree(work / "warmup", ignore_errors=True)
            warm_s = warm_up(lp, work / "warmup", size, tile, args.workers, args.variant)
            print(f"  warm-up (kernel cache): {warm_s:.1f} s", flush=True)
        runs = []
        for name, run in (("run1", run_uninterrupted), ("run2", run_killed)):
            out = work / name
            if out.exists():
                shutil.rmtree(out)
            print(f"  {name}:", flush=True)
            runs.append(run(lp, out, tile, args.workers, args.variant))
        (row1, ref), (row2, res) = runs
        same = identical(ref, res)
        del ref, res
    rows = [row1, row2]
    for r in rows:
        r.update(capture=capture, size=size, lights=lights, tile_size=tile,
                 workers=args.workers, peak_mib_worker_max=max(r["peak_mib_workers"]),
                 peak_text=", ".join(f"{p:.0f}" for p in r["peak_mib_workers"]))
    row1["identical_text"] = "reference"
    row2.update(identical=all(same.values()), identical_fields=same,
                identical_text=str(all(same.values())).lower())
    print()
    print_table(rows, COLUMNS)
    if not row2["identical"]:
        print("  differing: " + ", ".join(k for k, v in same.items() if not v))
    own = peak_rss_mib()
    print(f"  this process: peak {own:.0f} MiB ({render_peak:.0f} MiB after the capture); "
          f"identical: {str(row2['identical']).lower()}")
    meta = {"size": size, "lights": lights,
            "tile_size": tile, "workers": args.workers, "threads_per_worker": 1,
            "drjit_threads_per_tile": 2, "variant": args.variant, "noise": NOISE,
            "image_format": f"exr {BIT_DEPTH} bit, linear", "render_s": round(render_s, 2),
            "capture_reused": reused, "warmup_s": None if warm_s is None else round(warm_s, 2),
            "render_equals_synthetic_capture": check,
            "peak_mib_benchmark_process": round(own, 1),
            "peak_mib_benchmark_after_capture": round(render_peak, 1),
            "identical": row2["identical"]}
    path = save(args.out, "rti_tiles", rows, args.quick, **meta)
    _figure(args.out / "rti_tiles.png", rows)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
