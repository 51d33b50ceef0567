#!/usr/bin/env python3
"""Times the MRF engine's tile traces alone, per traced ray-voxel, for two revisions (#32 item 3).

A whole `mrfmap bench` also times what is not a tile trace (frames, bricks, the serial
applies of the traces' changes). This script builds each revision twice with a few lines of
instrumentation that are never committed:

- a *timed* build: the wall time of each keyframe update's parallel tile traces
  (`update_tiles`), and nothing in the traces themselves;
- a *counting* build: the same timer, and a count of the voxel crossings the traces process,
  with the rounding slivers (shorter than 1e-9 voxel edges, which session 19 stopped walking)
  counted apart. The count is a thread-local add in the loop over crossings: the same few
  instructions per crossing in either revision, but not the same time (session 38: 1.0 ns a
  crossing in dfa1c32, 0.2 ns in its main), so the timed builds give the fair ratio.

The crossings are the same in every run (the traces do not depend on the thread count), so
the counting builds run once each (`--counted-rounds`), and the timed builds `--rounds`
times, alternating. Printed per revision: the trace seconds (median), the crossings, and the
nanoseconds per crossing that is not a sliver, from the timed builds and, beside them, from
the counting builds (the figure sessions 19-37 reported). The two revisions' counts of
crossings that are not slivers should be equal when they walk the same voxels.

    python3 bench/trace_phase.py --base dfa1c32 --new HEAD ../shared/data/coffin-world \
        --resolution 0.02 --threads 2 --rounds 3

Needs git and cargo; builds into git worktrees /tmp/trace-phase-<rev>/ (counting) and
/tmp/trace-phase-<rev>-timed/ (about two minutes each), kept for the next run
(`git worktree remove --force DIR`). The instrumentation matches the trace's code by text; a
revision it does not recognise stops the script with the line it looked for.
"""

import argparse
import os
import re
import subprocess
import sys

TIMER = """use rayon::prelude::*;
static TRACE_NS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
"""

COUNTERS = TIMER + """static CROSSINGS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
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
            .map_init(SCRATCH::default, |scratch, &t| @TRACE@)
            .collect();
        {
            use std::sync::atomic::Ordering::Relaxed;
            let ns = TRACE_NS.fetch_add(t0.elapsed().as_nanos() as u64, Relaxed) + t0.elapsed().as_nanos() as u64;
            eprintln!("TRACE ns={} crossings={} slivers={}", ns, @COUNTS@);
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


def build(repo, rev, counting):
    """Builds `rev` timed or counting; returns its short sha and the binary."""
    sha = sh(["git", "-C", repo, "rev-parse", "--short", rev]).strip()
    tree = f"/tmp/trace-phase-{sha}" + ("" if counting else "-timed")
    if not os.path.isdir(tree):
        sh(["git", "-C", repo, "worktree", "add", "-f", "--detach", tree, sha])
    path = f"{tree}/crates/mrfmap/src/inference/mrf/trace.rs"
    src = open(path).read()
    if "TRACE_NS" not in src:
        collect = COLLECT.search(src)
        if "use rayon::prelude::*;" not in src or collect is None:
            sys.exit(f"{rev}: trace.rs has no `use rayon::prelude::*;` or no traces like\n{COLLECT.pattern}")
        timed = TIMED_COLLECT.replace("SCRATCH", collect.group(1))
        if counting:
            timed = timed.replace("@TRACE@", "{ let r = self.trace_tile(kf, &rays, t, scratch); flush(); r }")
            timed = timed.replace("@COUNTS@", "CROSSINGS.load(Relaxed), SLIVERS.load(Relaxed)")
        else:
            timed = timed.replace("@TRACE@", "self.trace_tile(kf, &rays, t, scratch)").replace("@COUNTS@", "0, 0")
        src = src[:collect.start()] + timed + src[collect.end():]
        src = src.replace("use rayon::prelude::*;", COUNTERS if counting else TIMER, 1)
        if counting:
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
    ap.add_argument("--rounds", type=int, default=3, help="runs of each timed build")
    ap.add_argument("--counted-rounds", type=int, default=1, help="runs of each counting build")
    a = ap.parse_args()
    repo = sh(["git", "rev-parse", "--show-toplevel"]).strip()
    builds = {counting: [build(repo, rev, counting) for rev in (a.base, a.new)] for counting in (True, False)}
    shas = [sha for sha, _ in builds[False]]
    runs = {(sha, counting): [] for sha in shas for counting in (True, False)}
    for counting, rounds in ((True, a.counted_rounds), (False, a.rounds)):
        for _ in range(rounds):
            for sha, binary in builds[counting]:
                runs[(sha, counting)].append(run(binary, a))
    median = lambda xs: sorted(xs)[len(xs) // 2]
    print(f"| revision | trace s, timed (median of {a.rounds}) | crossings | of which slivers "
          f"| ns per crossing, slivers left out: timed | counting (median of {a.counted_rounds}) |")
    print("|---|---|---|---|---|---|")
    per = {}
    for sha in shas:
        _, crossings, slivers = runs[(sha, True)][0]
        real = crossings - slivers
        timed, counted = (median([r[0] for r in runs[(sha, c)]]) for c in (False, True))
        per[sha] = (timed / real, counted / real)
        print(f"| {sha} | {timed / 1e9:.2f} | {crossings:,} | {slivers:,} | {per[sha][0]:.1f} | {per[sha][1]:.1f} |")
    base, new = shas
    print(f"\n{new} / {base}, per crossing that is not a sliver: timed {per[new][0] / per[base][0]:.3f}, "
          f"counting {per[new][1] / per[base][1]:.3f}")


if __name__ == "__main__":
    main()
