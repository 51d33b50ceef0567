"""Tiled maps built in parallel on Dask: one task per tile, on one machine or a cluster.

A map larger than one machine is built as a *tiled map* (a folder of tile map files and an
index, ``tiles.toml``; README "Tiled maps"). Every tile is built alone from the frames whose
rays can reach it, so tiles are independent tasks. Planning (which frames reach which tile)
reads every frame once; it too runs on the cluster, in chunks of frames, so that the client
reads no image and the workers share that pass. Then one task per tile builds it, and the
client writes the index when every tile is in.

>>> import mrfmap.distributed as md                                   # doctest: +SKIP
>>> md.build("floor/", "floor-tiles/", tile=10.0, resolution=0.05)    # doctest: +SKIP

- Workers read their frames from the dataset folder themselves: only paths and frame
  indices go through the scheduler, so inputs and the output folder must be on storage every
  worker sees (one machine; NFS or similar on a cluster; docs/distributed.md).
- Each task checks the tile's memory estimate against the worker's memory limit before it
  starts and refuses (``MemoryError``) rather than be killed half-way.
- Tasks that fail are retried (``retries``) and their error is raised if they still fail;
  tiles already written stay, but without the index the folder is not a map.
- Progress: Dask's dashboard, and ``distributed.progress`` on a terminal.
- Without ``client`` a ``LocalCluster`` of one single-threaded worker process per core runs
  the tasks and is closed at the end.

Dask is an optional extra: ``pip install mrfmap[distributed]``.
"""

import argparse
import os
import sys
import time
from typing import Any, Dict, List, Optional, Sequence

from . import _mrfmap

__all__ = ["build", "plan"]


def plan(source: str, *, tile: float, resolution: float, **options: Any) -> List[tuple]:
    """Which frames reach which tile: ``[((x, y, z), [frame, ...]), ...]``, reading every frame
    of the dataset folder ``source`` once (options as :func:`build`)."""
    return _mrfmap._plan_tiles(str(source), tile=tile, resolution=resolution, **options)


def _plan_chunk(source: str, frames: List[int], options: Dict[str, Any]) -> List[tuple]:
    """Planning of some frames, on a worker (its tasks' thread count)."""
    return _mrfmap._plan_tiles(source, frames, **options)


def _plan_on(client: Any, source: str, count: int, options: Dict[str, Any], retries: int) -> List[tuple]:
    """:func:`plan` of the ``count`` frames as tasks on ``client``'s workers, a few chunks of
    frames per worker (so a slow chunk does not hold the others up), merged in frame order."""
    workers = max(1, len(client.scheduler_info().get("workers", {})))
    size = max(1, -(-count // (4 * workers)))
    chunks = [list(range(i, min(i + size, count))) for i in range(0, count, size)]
    futures = [
        client.submit(_plan_chunk, source, chunk, options, retries=retries, pure=False, priority=1_000_000)
        for chunk in chunks
    ]
    merged: Dict[tuple, List[int]] = {}
    for part in client.gather(futures):
        for key, frames in part:
            merged.setdefault(tuple(key), []).extend(frames)
    return sorted((key, sorted(frames)) for key, frames in merged.items())


def _status_kib(field: str) -> Optional[int]:
    """A ``/proc/self/status`` field in KiB (Linux), else None."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _build_one(source: str, out_dir: str, key: tuple, frames: List[int], options: Dict[str, Any]) -> dict:
    """One tile, on a worker: the peak it expects (the worker's resident size now plus the
    tile's estimate) checked against the worker's limit, then built and written; returns its
    index entry, with that expected peak and (on Linux) the worker's resident size before the
    task and its peak during it (the peak is reset first), which the benchmark compares."""
    limit = None
    try:
        from distributed import get_worker

        limit = get_worker().memory_manager.memory_limit
    except (ImportError, ValueError, AttributeError):
        pass
    # The worker's size now plus what the tile's build adds: the peak this task expects.
    before = _status_kib("VmRSS")
    needed = (before or 0) * 1024 + _mrfmap._tile_estimate(source, key, frames, **options)
    if limit and needed > limit:
        raise MemoryError(
            f"tile {key}: the worker would need about {needed / 2**20:.0f} MiB to build it, more than its "
            f"limit of {limit / 2**20:.0f} MiB; use smaller tiles, a coarser resolution or workers with more memory"
        )
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # resets the peak resident size (VmHWM) of this process
    except OSError:
        before = None
    entry = _mrfmap._build_tile(source, out_dir, key, frames, **options)
    entry["estimate_bytes"] = needed
    if before is not None:
        entry["rss_before_kib"], entry["rss_peak_kib"] = before, _status_kib("VmHWM")
    return entry


def build(
    source: str,
    out_dir: str,
    *,
    tile: float,
    resolution: float,
    engine: str = "logodds",
    client: Optional[Any] = None,
    tile_height: Optional[float] = None,
    margin: Optional[float] = None,
    max_range: Optional[float] = None,
    bounds: Optional[Sequence[float]] = None,
    noise: Optional[str] = None,
    particles: Optional[int] = None,
    iterations: Optional[int] = None,
    prior: Optional[float] = None,
    threads_per_task: int = 1,
    workers: Optional[int] = None,
    retries: int = 2,
    progress: bool = True,
) -> Dict[str, Any]:
    """Builds the dataset folder ``source`` into the tiled map ``out_dir``, one Dask task per
    tile of ``tile`` metres in x and y (a whole number of 8-voxel bricks; columns through every
    height, or layers of ``tile_height`` metres), and returns a summary
    (``tiles``, ``voxels``, ``occupied``, ``frames``, ``tile_frames``, ``seconds``).

    ``engine``, ``resolution``, ``max_range``, ``bounds`` (``[xmin, ymin, zmin, xmax, ymax,
    zmax]``), ``noise`` (a ``noise.toml``), ``particles`` (CRM), ``iterations`` and ``prior``
    (MRF) are ``mrfmap build``'s options; ``margin``: metres around each tile its build maps
    too (default 0 for log-odds, whose tiles equal the map built whole, 1 m for MRF and CRM).
    ``client``: a ``distributed.Client`` (default: a ``LocalCluster`` of ``workers`` worker
    processes, default one per core). ``threads_per_task``: threads each tile's build uses.
    The summary's ``plan_seconds`` and ``cluster_seconds`` are the time spent planning (on
    the cluster's workers) and starting a local cluster (0 with a client); its ``entries`` are the tiles' index entries with their memory estimate and,
    on Linux, their worker's resident size before the task and peak during it.
    """
    options: Dict[str, Any] = {"tile": tile, "resolution": resolution, "engine": engine}
    extra = dict(
        tile_height=tile_height,
        margin=margin,
        max_range=max_range,
        noise=noise,
        particles=particles,
        iterations=iterations,
        prior=prior,
    )
    options.update({k: v for k, v in extra.items() if v is not None})
    if bounds is not None:
        options["bounds"] = list(bounds)
    source, out_dir = os.fspath(source), os.fspath(out_dir)
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise ValueError(f"{out_dir}: a tiled map is a folder, and this is a file")
    try:
        from distributed import Client, LocalCluster, progress as dask_progress
    except ImportError as e:
        raise ImportError("mrfmap.distributed needs Dask: pip install 'mrfmap[distributed]'") from e
    # The options are checked (and the dataset's poses read) here, before any cluster starts.
    count = _mrfmap._frame_count(source, **options)
    started = time.monotonic()
    task_options = dict(options, threads=threads_per_task)
    own = client is None
    cluster = None
    if own:
        if workers is None:
            workers = max(1, (os.cpu_count() or 1) // max(1, threads_per_task))
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
        client = Client(cluster)
    ready = time.monotonic()
    try:
        tiles = _plan_on(client, source, count, task_options, retries)
        planned = time.monotonic()
        if not tiles:
            raise ValueError(f"{source}: no frame reaches any tile (no valid depth within the bounds)")
        os.makedirs(out_dir, exist_ok=True)
        futures = [
            client.submit(
                _build_one,
                source,
                out_dir,
                key,
                frames,
                task_options,
                key=f"mrfmap-tile-{key[0]}_{key[1]}_{key[2]}-{os.path.abspath(out_dir)}",
                retries=retries,
                pure=False,
                # Largest tiles first, so that the last tasks are short (less idle at the end).
                priority=len(frames),
            )
            for key, frames in tiles
        ]
        if progress and sys.stderr.isatty():
            dask_progress(futures)
        entries = client.gather(futures)
    finally:
        if own:
            client.close()
            cluster.close()
    _mrfmap._write_tile_index(source, out_dir, entries, **options)
    return {
        "tiles": len(entries),
        "voxels": sum(e["voxels"] for e in entries),
        "occupied": sum(e["occupied"] for e in entries),
        "frames": len({f for _, frames in tiles for f in frames}),
        "tile_frames": sum(len(frames) for _, frames in tiles),
        "seconds": time.monotonic() - started,
        "plan_seconds": planned - ready,
        "cluster_seconds": ready - started,
        "entries": entries,
    }


def main(argv: Optional[Sequence[str]] = None) -> int:
    """``python -m mrfmap.distributed build DATASET OUT_DIR --tile T --resolution R ...``"""
    p = argparse.ArgumentParser(prog="python -m mrfmap.distributed", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="build a dataset folder into a tiled map on Dask")
    b.add_argument("source")
    b.add_argument("out_dir")
    b.add_argument("--tile", type=float, required=True, help="tile edge in metres (a whole number of bricks)")
    b.add_argument("--resolution", type=float, required=True)
    b.add_argument("--engine", default="logodds", choices=["logodds", "mrf", "crm"])
    b.add_argument("--scheduler", help="address of a running Dask scheduler (default: a local cluster)")
    b.add_argument("--tile-height", type=float, help="also cut tiles in z (default: columns)")
    b.add_argument("--margin", type=float)
    b.add_argument("--max-range", type=float)
    b.add_argument("--bounds", help="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX")
    b.add_argument("--noise")
    b.add_argument("--particles", type=int)
    b.add_argument("--iterations", type=int)
    b.add_argument("--prior", type=float)
    b.add_argument("--threads-per-task", type=int, default=1)
    b.add_argument("--workers", type=int, help="local cluster: worker processes (default: one per core)")
    b.add_argument("--retries", type=int, default=2)
    a = p.parse_args(argv)
    client = None
    if a.scheduler:
        from distributed import Client

        client = Client(a.scheduler)
    bounds = [float(v) for v in a.bounds.split(",")] if a.bounds else None
    try:
        summary = build(
            a.source,
            a.out_dir,
            tile=a.tile,
            resolution=a.resolution,
            engine=a.engine,
            client=client,
            tile_height=a.tile_height,
            margin=a.margin,
            max_range=a.max_range,
            bounds=bounds,
            noise=a.noise,
            particles=a.particles,
            iterations=a.iterations,
            prior=a.prior,
            threads_per_task=a.threads_per_task,
            workers=a.workers,
            retries=a.retries,
        )
    except (ValueError, OSError, MemoryError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(
        f"{a.out_dir}: {summary['tiles']} tiles, {summary['frames']} frames ({summary['tile_frames']} tile-frames), "
        f"{summary['voxels']} voxels ({summary['occupied']} occupied), {summary['seconds']:.1f} s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
