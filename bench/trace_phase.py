#!/usr/bin/env python3
"""Times the MRF engine's tile traces alone, per traced ray-voxel, for two revisions (#32 item 3).

A whole `mrfmap bench` also times what is not a tile trace (frames, bricks, the serial
applies of the traces' changes). This script builds both revisions with a few lines of
instrumentation that are never committed: the wall time of each keyframe update's parallel
tile traces (`update_tiles`), and a count of the voxel crossings the traces process, with
the rounding slivers (shorter than 1e-9 voxel edges, which session 19 stopped walking)
counted apart. It then runs `mrfmap bench` with each, alternating, and prints per revision
the trace seconds, the crossings, and the nanoseconds per crossing that is not a sliver (the
two revisions' counts of those should be equal when they walk the same voxels).

    python3 bench/trace_phase.py --base dfa1c32 --new HEAD ../shared/data/coffin-world \
        --resolution 0.02 --threads 2 --rounds 3

Needs git and cargo; builds into git worktrees /tmp/trace-phase-<rev>/ (about two minutes
each), kept for the next run (`git worktree remove --force /tmp/trace-phase-<rev>`). The
instrumentation matches the trace's code by text; a revision it does not recognise stops the
script with the line it looked for.
"""

import argparse
import os
import re
import subprocess
import sys

COUNTERS = """use rayon::prelude::*;
static TRACE_NS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
static CROSSINGS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
static SLIVERS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
thread_local! { static LOCAL: std::cell::Cell<(u64, u64)> = const { std::cell::Cell::new((0, 0)) }; }
#[inline(always)]
fn count(sliver: bool) { LOCAL.with(|c| { let (a, b) = c.get(); c.set((a + 1, b + sliver as u64)); }); }
fn flush() {
    use std::sync::atomic::Ordering::Relaxed;
    LOCAL.with(|c| { let (a, b) = c.replace((0, 0)); CROSSINGS.fetch_add(a, Relaxed); SLIVERS.fetch_add(b, Relaxed); });
}
"""

# The parallel traces of one keyframe update, however formatted, with the per-thread buffers'
# type (`TileScratch` until session 37, `Scratch` since); and the timed version of it.
COLLECT = re.compile(r"let pending: Vec<Traced> =\s*tiles\s*\.par_iter\(\)\s*"
                     r"\.map_init\((\w+)::default, \|scratch, &t\| self\.trace_tile\(kf, &rays, t, scratch\)\)\s*"
                     r"\.collect\(\);")

TIMED_COLLECT = """let t0 = std::time::Instant::now();
        let pending: Vec<Traced> = tiles
            .par_iter()
            .map_init(SCRATCH::default, |scratch, &t| { let r = self.trace_tile(kf, &rays, t, scratch); flush(); r })
            .collect();
        {
            use std::sync::atomic::Ordering::Relaxed;
            let ns = TRACE_NS.fetch_add(t0.elapsed().as_nanos() as u64, Relaxed) + t0.elapsed().as_nanos() as u64;
            eprintln!("TRACE ns={} crossings={} slivers={}", ns, CROSSINGS.load(Relaxed), SLIVERS.load(Relaxed));
        }"""

# Where each generation of the trace handles one crossing, and the counting line to add.
CROSSING_SITES = [
    # Session 37 and later: the visit one level deeper (a ray's walk in a loop).
    ("                                    if edges < SLIVER {\n                                        return;\n                                    }",
     "\n                                    count(false);"),
    # Sessions 19 to 36: slivers are skipped before anything else.
    ("                                if edges < SLIVER {\n                                    return;\n                                }",
     "\n                                count(false);"),
    # Before session 19 (dfa1c32): every crossing of an allocated voxel, slivers included.
    ("                        if let Some(&s) = s {\n                            let length = c.length();",
     "\n                            count(length * inv_r < 1e-9);"),
]


def sh(cmd, **kw):
    return subprocess.run(cmd, check=True, text=True, capture_output=True, **kw).stdout


def build(repo, rev):
    sha = sh(["git", "-C", repo, "rev-parse", "--short", rev]).strip()
    tree = f"/tmp/trace-phase-{sha}"
    if not os.path.isdir(tree):
        sh(["git", "-C", repo, "worktree", "add", "-f", "--detach", tree, sha])
    path = f"{tree}/crates/mrfmap/src/inference/mrf/trace.rs"
    src = open(path).read()
    if "TRACE_NS" not in src:
        collect = COLLECT.search(src)
        if "use rayon::prelude::*;" not in src or collect is None:
            sys.exit(f"{rev}: trace.rs has no `use rayon::prelude::*;` or no traces like\n{COLLECT.pattern}")
        timed = TIMED_COLLECT.replace("SCRATCH", collect.group(1))
        src = src[:collect.start()] + timed + src[collect.end():]
        src = src.replace("use rayon::prelude::*;", COUNTERS, 1)
        site = next((s for s in CROSSING_SITES if s[0] in src), None)
        if site is None:
            sys.exit(f"{rev}: trace.rs has none of the known crossing sites")
        src = src.replace(site[0], site[0] + site[1])
        open(path, "w").write(src)
    subprocess.run(["cargo", "build", "--release", "-q", "-p", "mrfmap-cli"], cwd=tree, check=True,
                   env={**os.environ, "CARGO_TARGET_DIR": f"{tree}/target"})
    return sha, f"{tree}/target/release/mrfmap"


def run(binary, a):
    p = subprocess.run([binary, "-q", "bench", a.dataset, "--engine", "mrf", "--resolutions", a.resolution,
                        "--repeat", "1", "--threads", str(a.threads)], capture_output=True, text=True, check=True)
    last = re.findall(r"TRACE ns=(\d+) crossings=(\d+) slivers=(\d+)", p.stderr)[-1]
    return tuple(int(x) for x in last)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--base", required=True)
    ap.add_argument("--new", default="HEAD")
    ap.add_argument("--resolution", default="0.02")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    repo = sh(["git", "rev-parse", "--show-toplevel"]).strip()
    revs = [build(repo, a.base), build(repo, a.new)]
    runs = {sha: [] for sha, _ in revs}
    for _ in range(a.rounds):
        for sha, binary in revs:
            runs[sha].append(run(binary, a))
    print(f"| revision | trace s (median of {a.rounds}) | crossings | of which slivers | ns per crossing, slivers left out |")
    print("|---|---|---|---|---|")
    per = {}
    for sha, _ in revs:
        ns = sorted(r[0] for r in runs[sha])[len(runs[sha]) // 2]
        _, crossings, slivers = runs[sha][0]
        per[sha] = ns / (crossings - slivers)
        print(f"| {sha} | {ns / 1e9:.2f} | {crossings:,} | {slivers:,} | {per[sha]:.1f} |")
    (base, _), (new, _) = revs
    print(f"\n{new} / {base}, per crossing that is not a sliver: {per[new] / per[base]:.3f}")


if __name__ == "__main__":
    main()
