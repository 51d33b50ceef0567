#!/usr/bin/env bash
# The MRF's online schedule against its batch build (issue #32): streams DATASET's frames
# with `build --online --budget-ms MS`, builds the batch map of the same keyframes with the
# default schedule, and scores both on the held-out view (reference metric, --sigma-model).
# Prints the per-keyframe ms (median, 95th percentile, and the 95th percentile over two
# ranges of keyframes), peak RSS and both accuracies.
#
# usage: bench/online.sh DATASET RESOLUTION BUDGET_MS HELD_OUT_VIEW OUT_DIR [BUILD OPTIONS...]
# e.g.:  bench/online.sh ../shared/data/coffin-world 0.02 2000 6 /tmp/on --bounds -2,-2,0,2,2,3
# Needs a release build (target/release/mrfmap) and GNU time (/usr/bin/time).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
mrfmap=${MRFMAP:-$root/target/release/mrfmap}
data=$1 res=$2 budget=$3 view=$4 out=$5
shift 5
mkdir -p "$out"
run() { # NAME ARGS...: builds, keeps the peak RSS
  local name=$1
  shift
  /usr/bin/time -f "%M" -o "$out/$name.rss" "$mrfmap" -q build "$data" -o "$out/$name.mrfmap" \
    --resolution "$res" --engine mrf --exclude "$view" "$@"
}
run online --online --budget-ms "$budget" --timings "$out/timings.csv" "$@" >/dev/null
run batch "$@" >/dev/null
score() {
  "$mrfmap" eval "$out/$1.mrfmap" "$data" --views "$view" --metric reference --sigma-model --json |
    python3 -c 'import json, sys; print("%.4f" % json.load(sys.stdin)["accuracy"])'
}
python3 - "$out/timings.csv" "$(score online)" "$(score batch)" "$(cat "$out/online.rss")" "$(cat "$out/batch.rss")" <<'PY'
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
ms = [float(r["ms"]) for r in rows]
def p95(xs):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(0.95 * (len(xs) - 1))))] if xs else float("nan")
n = len(ms)
early, late = ms[4:15], ms[49:61]
print(f"keyframes {n}  ms median {sorted(ms)[n // 2]:.0f}  p95 {p95(ms):.0f}  max {max(ms):.0f}", end="")
if late:
    print(f"  p95 kf 5-15 {p95(early):.0f}  p95 kf 50-61 {p95(late):.0f}  ratio {p95(late) / p95(early):.2f}", end="")
print(f"\nlast backlog {rows[-1]['backlog_tiles']} tiles")
print(f"held-out accuracy: online {sys.argv[2]}  batch {sys.argv[3]}  (online - batch {float(sys.argv[2]) - float(sys.argv[3]):+.4f})")
print(f"peak RSS MiB: online {int(sys.argv[4]) / 1024:.0f}  batch {int(sys.argv[5]) / 1024:.0f}")
PY
