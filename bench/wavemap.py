#!/usr/bin/env python3
"""Log-odds against wavemap and OctoMap on the same frames, alternating (issue #34).

usage: bench/wavemap.py [--resolutions 0.05,0.02] [--threads 1,2] [--rounds 3] [--max-range 6]
                        [--octomap-max-frames 20] [--marking project|walk|centres] DATASET...

Per dataset, resolution and thread count, each round runs `wavemap_build` (bench/wavemap/,
built by bench/wavemap/build_wavemap.sh) and `mrfmap build --engine logodds`, the order swapped
every round, and OctoMap (bench/octomap_driver.cpp, single-threaded; one run per dataset and
resolution, only for datasets of at most --octomap-max-frames frames: it takes seconds per
frame at 0.02 m). Per run: each tool's own integration time per frame (no PNG decoding), the
whole process's wall time per frame, and its peak RSS (GNU time's %M: a child's `ru_maxrss` as
Python's own wait4 reads it starts at the RSS of the process that forked it, Python's 14-15
MiB, which hid every peak below that). Prints one Markdown table row per setting (medians over
rounds; ratios are of medians) for BENCHMARKS.md: integration times to 0.01 ms and their ratio
to 0.001, so that a row decides the 0.67 target without rounding (at 2.6 ms a frame, 0.1 ms is 4%).

Semantics that differ (say them beside the numbers): wavemap marks a band in front of and
behind each hit instead of the end voxel, cuts its max range on z-depth (we and OctoMap cut
the range along the ray), updates free space at coarse octree levels (not voxel by voxel) and
is compiled with -march=native; its occupied cells are counted at the finest level.
Standard library only; run from the repository root after `cargo build --release` (or, to
measure the build `cargo install --profile dist` installs, `cargo build --profile dist -p
mrfmap-cli` and `--mrfmap target/dist/mrfmap`: BENCHMARKS.md says which build each table used).
"""
import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import time

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("datasets", nargs="+")
ap.add_argument("--resolutions", default="0.05,0.02")
ap.add_argument("--threads", default="1,2")
ap.add_argument("--rounds", type=int, default=3)
ap.add_argument("--max-range", type=float, default=6.0)
ap.add_argument("--octomap-max-frames", type=int, default=20)
ap.add_argument("--wavemap", default=os.environ.get("WAVEMAP_BIN", "/tmp/wavemap-bin/wavemap_build"))
ap.add_argument("--octomap", default="target/bench/octomap_driver")
ap.add_argument("--mrfmap", default="target/release/mrfmap")
ap.add_argument("--marking", default="project", help="mrfmap's --marking (centres: the approximate model)")
ap.add_argument("--out", default="/tmp/mrfmap-wavemap-bench")
a = ap.parse_args()
for tool, path, how in (("wavemap", a.wavemap, "bench/wavemap/build_wavemap.sh"),
                        ("mrfmap", a.mrfmap, "cargo build --release"),
                        ("GNU time", "/usr/bin/time", "Debian package `time`")):
    if not os.access(path, os.X_OK):
        sys.exit(f"{tool} binary {path} not found (see {how})")
os.makedirs(a.out, exist_ok=True)
med = statistics.median


def run(cmd):
    """(wall seconds, stdout, peak RSS MiB) of one child process."""
    t0 = time.perf_counter()
    p = subprocess.run(["/usr/bin/time", "-f", "MAXRSS_KIB %M"] + cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        sys.exit(f"failed ({p.returncode}): {' '.join(cmd)}\n{p.stderr[-2000:]}")
    rss = int(re.findall(r"MAXRSS_KIB (\d+)", p.stderr)[-1])
    return wall, p.stdout, rss / 1024.0


def frames_of(ds):
    with open(f"{ds}/depth.txt") as f:
        return sum(1 for line in f if line.strip() and not line.startswith("#"))


def wavemap(ds, res, threads):
    wall, out, rss = run([a.wavemap, ds, "--cell-width", res, "--max-range", str(a.max_range),
                          "--threads", str(threads)])
    kv = dict(t.split("=", 1) for t in out.split() if "=" in t)
    return dict(integ=float(kv["seconds_per_frame"]) * 1e3, wall=wall, rss=rss, occ=int(kv["occupied_cells"]))


def mrfmap(ds, res, threads, mapf):
    cmd = [a.mrfmap, "build", ds, "-o", mapf, "--engine", "logodds", "--resolution", res, "--quiet",
           "--threads", str(threads), "--marking", a.marking] + (["--max-range", str(a.max_range)] if a.max_range > 0 else [])
    wall, out, rss = run(cmd)
    m = re.search(r"(\d+) frames, (\d+) voxels \((\d+) occupied\), ([0-9.]+) ms/frame", out)
    return dict(integ=float(m.group(4)), wall=wall, rss=rss, occ=int(m.group(3)))


def octomap(ds, res):
    wall, out, rss = run([a.octomap, ds, res, "1", "-", str(a.max_range if a.max_range > 0 else -1)])
    _, ms, occ, _ = out.split()
    return dict(integ=float(ms), wall=wall, rss=rss, occ=int(occ))


print("| dataset | res (m) | threads | integration ms/frame: wavemap / OctoMap / mrfmap | mrfmap / wavemap | "
      "whole process ms/frame: wavemap / mrfmap | ratio | peak RSS MiB: wavemap / OctoMap / mrfmap | ratio | "
      "occupied: wavemap / OctoMap / mrfmap | mrfmap bytes per voxel |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
log = open(f"{a.out}/runs.jsonl", "a")
for ds in a.datasets:
    name, nf = os.path.basename(ds.rstrip("/")), frames_of(ds)
    for res in a.resolutions.split(","):
        o = octomap(ds, res) if nf <= a.octomap_max_frames and os.access(a.octomap, os.X_OK) else None
        for threads in a.threads.split(","):
            mapf = f"{a.out}/{name}-{res}-t{threads}.mrfmap"
            runs = {"w": [], "m": []}
            for rnd in range(a.rounds):
                for tool in ("wm" if rnd % 2 == 0 else "mw"):
                    r = wavemap(ds, res, threads) if tool == "w" else mrfmap(ds, res, threads, mapf)
                    runs[tool].append(r)
                    log.write(json.dumps(dict(tool=tool, ds=name, res=res, threads=threads, **r)) + "\n")
            log.flush()
            w = {k: med(r[k] for r in runs["w"]) for k in ("integ", "wall", "rss")}
            m = {k: med(r[k] for r in runs["m"]) for k in ("integ", "wall", "rss")}
            info = json.loads(subprocess.run([a.mrfmap, "info", mapf, "--json"], capture_output=True,
                                             check=True, text=True).stdout)
            on = (lambda k, f: format(o[k], f)) if o else (lambda k, f: "not run")
            print(f"| {name} ({nf}) | {res} | {threads} | {w['integ']:.2f} / {on('integ', '.1f')} / {m['integ']:.2f} "
                  f"| {m['integ'] / w['integ']:.3f} | {w['wall'] / nf * 1e3:.1f} / {m['wall'] / nf * 1e3:.1f} "
                  f"| {m['wall'] / w['wall']:.2f} | {w['rss']:.1f} / {on('rss', '.1f')} / {m['rss']:.1f} "
                  f"| {m['rss'] / w['rss']:.2f} | {runs['w'][-1]['occ']} / {on('occ', 'd')} / {runs['m'][-1]['occ']} "
                  f"| {info['bytes_per_voxel']:.1f} |", flush=True)
