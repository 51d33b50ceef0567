#!/usr/bin/env python3
"""Tiled log-odds builds on Dask with 1 and 2 local worker processes (issue #36's scaling
target), on a dataset folder (the 2,000-frame floor: `mrfmap simulate
results/scenes/floor.toml DIR`). Per run: wall time, tiles, tile-frames; per tile: its memory
estimate against the growth of its worker's resident size during the task (peak minus the
size before; the allocator keeps what earlier tasks freed, so later tasks grow less) and the
worker's whole peak. Needs the mrfmap wheel with its `distributed` extra.

usage: bench/distributed.py DATASET OUT_DIR [--tile 10] [--resolution 0.05] [--repeat 1]
"""
import argparse
import os
import shutil
import statistics

import mrfmap.distributed as md

p = argparse.ArgumentParser()
p.add_argument("dataset")
p.add_argument("out")
p.add_argument("--tile", type=float, default=10.0)
p.add_argument("--resolution", type=float, default=0.05)
p.add_argument("--repeat", type=int, default=1)
a = p.parse_args()
base = 12 * 2**20  # the estimate's BASE_MEMORY: the program and decoded frames
times = {}
for rep in range(a.repeat):
    for workers in (1, 2):
        out = os.path.join(a.out, f"w{workers}")
        shutil.rmtree(out, ignore_errors=True)
        s = md.build(a.dataset, out, tile=a.tile, resolution=a.resolution, workers=workers, progress=False)
        times.setdefault(workers, []).append(s["seconds"])
        grow = [
            ((e["rss_peak_kib"] - e["rss_before_kib"]) * 1024, e["estimate_bytes"], e["rss_peak_kib"] * 1024)
            for e in s["entries"]
            if "rss_peak_kib" in e
        ]
        ratios = [g / max(est - base, 1) for g, est, _ in grow]
        worst = max(grow, key=lambda g: g[0])
        print(
            f"run {rep + 1} workers {workers}: {s['seconds']:.1f} s, {s['tiles']} tiles, {s['frames']} frames, "
            f"{s['tile_frames']} tile-frames, {s['voxels']} voxels; task growth / (estimate - base): "
            f"median {statistics.median(ratios):.2f}, max {max(ratios):.2f}; largest growth "
            f"{worst[0] / 2**20:.1f} MiB (estimate {worst[1] / 2**20:.1f} MiB); worker peak "
            f"{max(g[2] for g in grow) / 2**20:.0f} MiB"
        )
t1, t2 = statistics.median(times[1]), statistics.median(times[2])
print(f"median: 1 worker {t1:.1f} s, 2 workers {t2:.1f} s, speed-up {t1 / t2:.2f}x")
