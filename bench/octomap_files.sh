#!/usr/bin/env bash
# Checks `mrfmap export --bt` against OctoMap itself: builds a log-odds map of a dataset with
# mrfmap and with OctoMap 1.9 (bench/octomap_driver.cpp, `OcTree::insertPointCloud` then
# `writeBinary`), and compares the two .bt files' tree data byte for byte, and the trees
# with OctoMap's `compare_octrees`. Not part of CI (needs apt for liboctomap-dev).
#
# usage: bench/octomap_files.sh [DATASET] [RESOLUTION]
set -euo pipefail
cd "$(dirname "$0")/.."
ds=${1:-../shared/data/icl-livingroom-5}
res=${2:-0.05}

if ! pkg-config --exists octomap libpng 2>/dev/null || ! command -v compare_octrees >/dev/null; then
  echo "installing liboctomap-dev libpng-dev pkg-config octomap-tools (Debian)" >&2
  apt-get update -qq && apt-get install -y -qq liboctomap-dev libpng-dev pkg-config octomap-tools >/dev/null
fi
mkdir -p target/bench
g++ -O2 -std=c++17 bench/octomap_driver.cpp -o target/bench/octomap_driver $(pkg-config --cflags --libs octomap libpng)
cargo build --release -q -p mrfmap-cli
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT

target/bench/octomap_driver "$ds" "$res" 1 "$out/octomap.bt" > /dev/null
target/release/mrfmap -q build "$ds" -o "$out/ours.mrfmap" --resolution "$res"
target/release/mrfmap export "$out/ours.mrfmap" --bt "$out/ours.bt" --ot "$out/ours.ot"
python3 - "$out/ours.bt" "$out/octomap.bt" <<'PY'
import sys
a, b = (open(p, 'rb').read() for p in sys.argv[1:3])
da, db = (x[x.index(b'data\n') + 5:] for x in (a, b))
print(f"tree data: ours {len(da)} bytes, OctoMap's {len(db)} bytes, identical: {da == db}")

PY
convert_octree "$out/ours.bt" "$out/ours_bt.ot" > /dev/null
convert_octree "$out/octomap.bt" "$out/octomap_bt.ot" > /dev/null
compare_octrees "$out/ours_bt.ot" "$out/octomap_bt.ot" 2>&1 | grep -E "Expanded|KLD"
