#!/usr/bin/env python3
"""Two mrfmap binaries' log-odds builds side by side, alternating (issue #34's A/B checks).

usage: bench/logodds_ab.py OLD_BINARY NEW_BINARY [PAIRS] [DATA_DIR]

For icl-livingroom-5, coffin-world and icl-livingroom1 (under DATA_DIR, default
../shared/data) at 0.05 and 0.02 m on 1 and 2 threads, runs `mrfmap build DATASET --engine
logodds --max-range 6` PAIRS times (default 5) with each binary, the order swapped every pair.
Prints a Markdown row per setting: the median integration ms/frame (as `build` prints it) of
each, the median and range of the pairs' ratios NEW / OLD, the same for the whole process's
wall time, and the median peak RSS (GNU time's %M). Standard library only.
"""
import re
import statistics
import subprocess
import sys
import time

old, new = sys.argv[1], sys.argv[2]
pairs = int(sys.argv[3]) if len(sys.argv) > 3 else 5
data = sys.argv[4] if len(sys.argv) > 4 else "../shared/data"


def run(binary, ds, res, threads):
    """(integration ms/frame, wall seconds, peak RSS MiB) of one build."""
    t0 = time.perf_counter()
    p = subprocess.run(["/usr/bin/time", "-f", "MAXRSS_KIB %M", binary, "build", f"{data}/{ds}", "-o",
                        "/tmp/logodds_ab.mrfmap", "--engine", "logodds", "--resolution", res, "--quiet",
                        "--threads", threads, "--max-range", "6"], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        sys.exit(f"{binary} failed on {ds} {res}: {p.stderr[-2000:]}")
    ms = float(re.search(r"([0-9.]+) ms/frame", p.stdout).group(1))
    return ms, wall, int(re.findall(r"MAXRSS_KIB (\d+)", p.stderr)[-1]) / 1024


print("| dataset | res (m) | threads | integration ms/frame, old / new | ratio (range) | "
      "whole process ratio (range) | peak RSS MiB, old / new |")
print("|---|---|---|---|---|---|---|")
for ds in ["icl-livingroom-5", "coffin-world", "icl-livingroom1"]:
    for res in ["0.05", "0.02"]:
        for threads in ["1", "2"]:
            a, b = [], []
            for i in range(pairs):
                for binary, out in ([(old, a), (new, b)] if i % 2 == 0 else [(new, b), (old, a)]):
                    out.append(run(binary, ds, res, threads))
            med = lambda runs, k: statistics.median(r[k] for r in runs)
            integ = [y[0] / x[0] for x, y in zip(a, b)]
            wall = [y[1] / x[1] for x, y in zip(a, b)]
            print(f"| {ds} | {res} | {threads} | {med(a, 0):.1f} / {med(b, 0):.1f} | "
                  f"{statistics.median(integ):.2f} ({min(integ):.2f}-{max(integ):.2f}) | "
                  f"{statistics.median(wall):.2f} ({min(wall):.2f}-{max(wall):.2f}) | "
                  f"{med(a, 2):.1f} / {med(b, 2):.1f} |", flush=True)
