#!/bin/bash
# The memory estimate against the measured peak (resident, GNU time's %M) of real builds:
# prints one markdown row per build (data, engine, resolution, extra flags, estimate MiB,
# peak MiB, ratio). Needs ../shared/data (coffin-world, icl-livingroom1, intel-lab), a
# release build (cargo build --release -p mrfmap-cli) and /usr/bin/time. About 15 minutes;
# CRM at 0.01 m on coffin-world peaks at 9 GB.
# usage: bench/memory_estimates.sh [MRFMAP_BINARY]
set -u
bin=${1:-./target/release/mrfmap}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
run() { name=$1; data=$2; eng=$3; res=$4; shift 4
  out=$tmp/map.mrfmap
  line=$( { /usr/bin/time -f "PEAK %M" $bin build $data --engine $eng --resolution $res -o $out -v "$@" 2>&1; } | grep -E "memory estimate|PEAK" | tr '\n' ' ')
  est=$(echo "$line" | sed -E 's/.*memory estimate ([0-9.]+ [KMG]iB).*/\1/')
  peak=$(echo "$line" | sed -E 's/.*PEAK ([0-9]+).*/\1/')
  python3 -c "
import sys
e='$est'.split(); v=float(e[0])*{'KiB':1024,'MiB':2**20,'GiB':2**30}[e[1]]
p=$peak*1024
print(f'| $name | $eng | $res | $* | {v/2**20:.0f} | {p/2**20:.0f} | {v/p:.2f} |')"
}
D=${MRFMAP_SHARED_DATA:-../shared/data}
C=$D/coffin-world; I=$D/icl-livingroom1; L=$D/intel-lab/intel-corrected.log.gz
B=--bounds=-2,-2,0,2,2,3
for r in 0.05 0.02 0.01; do run coffin-world $C logodds $r; done
for r in 0.05 0.02; do run coffin-world $C crm $r; done
run coffin-world $C crm 0.01 $B
for r in 0.05 0.02; do run coffin-world $C mrf $r; done
run coffin-world $C mrf 0.01 $B
for r in 0.05 0.02 0.01; do run icl-livingroom1 $I logodds $r; done
run icl-livingroom1 $I mrf 0.05 --keyframes auto
run icl-livingroom1 $I mrf 0.02 --keyframes auto
for r in 0.05 0.02; do run intel-lab $L logodds $r; run intel-lab $L crm $r; done
run intel-lab $L logodds 0.01
# Misses clearing up to the laser's 80 m (the default clears 5 m): ten times the map.
for r in 0.05 0.02; do run intel-lab $L logodds $r --miss-range inf; run intel-lab $L crm $r --miss-range inf; done
