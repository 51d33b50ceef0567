#!/usr/bin/env bash
# Times mrfmap's log-odds engine against OctoMap 1.9 (Debian's liboctomap-dev) on the same
# frames, same resolutions, same machine, in one run. Not part of CI.
#
# usage: bench/peers.sh [--append] [DATASET ...]
#   default datasets: ../shared/data/icl-livingroom-5 ../shared/data/coffin-world
#   --append adds the table to BENCHMARKS.md
# env: RESOLUTIONS="0.05 0.02 0.01"  REPEAT=3
set -euo pipefail
cd "$(dirname "$0")/.."

append=0
if [[ "${1:-}" == "--append" ]]; then append=1; shift; fi
datasets=("$@")
[[ ${#datasets[@]} -gt 0 ]] || datasets=(../shared/data/icl-livingroom-5 ../shared/data/coffin-world)
resolutions=(${RESOLUTIONS:-0.05 0.02 0.01})
repeat=${REPEAT:-3}

if ! pkg-config --exists octomap libpng 2>/dev/null; then
  echo "installing liboctomap-dev libpng-dev pkg-config (Debian)" >&2
  apt-get update -qq && apt-get install -y -qq liboctomap-dev libpng-dev pkg-config >/dev/null
fi
mkdir -p target/bench
g++ -O2 -std=c++17 bench/octomap_driver.cpp -o target/bench/octomap_driver $(pkg-config --cflags --libs octomap libpng)
cargo build --release -q -p mrfmap-cli

rows=$(mktemp)
trap 'rm -f "$rows"' EXIT
for ds in "${datasets[@]}"; do
  name=$(basename "$ds")
  frames=$(grep -vc '^#' "$ds/depth.txt")
  for r in "${resolutions[@]}"; do
    # OctoMap: single-threaded (it has no parallel insert). Columns: res ms occupied leaves.
    o_mem=$( { /usr/bin/time -f '%M' target/bench/octomap_driver "$ds" "$r" "$repeat" > "$rows.o"; } 2>&1 | tail -1)
    read -r _ o_ms o_occ _ < "$rows.o"
    m_mem=$( { /usr/bin/time -f '%M' target/release/mrfmap -q bench "$ds" --resolutions "$r" --repeat "$repeat" > "$rows.m"; } 2>&1 | tail -1)
    read -r _ m_ms m_occ _ _ < <(grep -v '^#' "$rows.m" | tail -1)
    # The same engine walking every ray instead of projecting (the previous method).
    target/release/mrfmap -q bench "$ds" --resolutions "$r" --repeat "$repeat" --marking walk > "$rows.w"
    read -r _ w_ms _ _ _ < <(grep -v '^#' "$rows.w" | tail -1)
    ratio=$(python3 -c "print(f'{$o_ms / $m_ms:.1f}')")
    diff=$(python3 -c "print(f'{100.0 * ($m_occ - $o_occ) / $o_occ:+.2f}')")
    w_ratio=$(python3 -c "print(f'{$o_ms / $w_ms:.1f}')")
    printf '| %s (%s frames) | %s | %s | %s | %sx | %s (%sx) | %s | %s | %s%% | %s | %s |\n' \
      "$name" "$frames" "$r" "$o_ms" "$m_ms" "$ratio" "$w_ms" "$w_ratio" "$o_occ" "$m_occ" "$diff" \
      "$((o_mem / 1024))" "$((m_mem / 1024))" | tee -a "$rows"
  done
done

{
  echo
  echo "### $(date -u +%Y-%m-%d): log-odds vs OctoMap ($(nproc) cores, mrfmap on all, OctoMap single-threaded)"
  echo
  echo "Command: \`bench/peers.sh${*:+ $*}\` (best of $repeat per cell; time per frame of insertion only, frames preloaded)"
  echo
  echo "| dataset | res (m) | OctoMap ms/frame | mrfmap ms/frame | speed-up | mrfmap walking every ray, ms/frame | OctoMap occupied | mrfmap occupied | diff | OctoMap peak MiB | mrfmap peak MiB |"
  echo "|---|---|---|---|---|---|---|---|---|---|---|"
  cat "$rows"
} > "$rows.table"
cat "$rows.table"
if [[ $append == 1 ]]; then cat "$rows.table" >> BENCHMARKS.md; fi
rm -f "$rows.o" "$rows.m" "$rows.w" "$rows.table"
