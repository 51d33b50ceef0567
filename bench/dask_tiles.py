#!/usr/bin/env python3
"""Tiled log-odds builds on Dask with 1 and 2 local worker processes (issue #36's scaling
target), on a dataset folder (the 2,000-frame floor: `mrfmap simulate
results/scenes/floor.toml DIR`). Per run: wall time, tiles, tile-frames; per tile: its memory
worker's peak resident size during the task against the peak the task expected (the worker's
size before it plus the tile's estimate; the allocator keeps what earlier tasks freed, so the
size before includes some of it). Needs the mrfmap wheel with its `distributed` extra.

usage: bench/dask_tiles.py DATASET OUT_DIR [--tile 10] [--resolution 0.05] [--repeat 1]
"""
import argparse
import os
import shutil
import statistics

import mrfmap.distributed as md

def main():
    p = argparse.ArgumentParser()
    p.add_argument("dataset")
    p.add_argument("out")
    p.add_argument("--tile", type=float, default=10.0)
    p.add_argument("--resolution", type=float, default=0.05)
    p.add_argument("--repeat", type=int, default=1)
    a = p.parse_args()
    times = {}
    for rep in range(a.repeat):
        for workers in (1, 2):
            out = os.path.join(a.out, f"w{workers}")
            shutil.rmtree(out, ignore_errors=True)
            s = md.build(a.dataset, out, tile=a.tile, resolution=a.resolution, workers=workers, progress=False)
            times.setdefault(workers, []).append(s["seconds"])
            # Per tile: the worker's peak during the task over the peak the task expected.
            ratios = [e["rss_peak_kib"] * 1024 / e["estimate_bytes"] for e in s["entries"] if "rss_peak_kib" in e]
            peak = max(e["rss_peak_kib"] for e in s["entries"] if "rss_peak_kib" in e) / 1024
            print(
                f"run {rep + 1} workers {workers}: {s['seconds']:.1f} s (planning {s['plan_seconds']:.1f} s, cluster start "
                f"{s['cluster_seconds']:.1f} s), {s['tiles']} tiles, {s['frames']} frames, "
                f"{s['tile_frames']} tile-frames, {s['voxels']} voxels; worker peak / expected peak per tile: "
                f"median {statistics.median(ratios):.2f}, min {min(ratios):.2f}, max {max(ratios):.2f}; "
                f"largest worker peak {peak:.0f} MiB"
            )
    t1, t2 = statistics.median(times[1]), statistics.median(times[2])
    print(f"median: 1 worker {t1:.1f} s, 2 workers {t2:.1f} s, speed-up {t1 / t2:.2f}x")


if __name__ == "__main__":  # worker processes are spawned: they import this file
    main()
