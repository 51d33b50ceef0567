#!/usr/bin/env bash
# Held-out accuracy of tiled maps against maps built whole (issue #36): the simulated
# 40 m x 40 m floor (results/scenes/floor.toml), every 4th frame built at 0.05 m, 20 views in
# between scored (reference metric, --sigma-model: the Table I protocol), for each engine whole
# and in 10 m tiles (default margins). Prints one line per map; writes into OUT.
#
# usage: bench/tiles_accuracy.sh MRFMAP_BINARY OUT_DIR [ENGINES...]   (default: logodds crm mrf)
set -euo pipefail
bin=$1 out=$2
shift 2
engines=${*:-logodds crm mrf}
root=$(cd "$(dirname "$0")/.." && pwd)
mkdir -p "$out"
[ -d "$out/floor" ] || "$bin" simulate "$root/results/scenes/floor.toml" "$out/floor" -q
frames=$(seq -s, 0 4 1996)
views=$(seq -s, 2 100 1902)
for engine in $engines; do
  for kind in whole tiled; do
    map="$out/$engine-$kind"
    extra=()
    if [ "$kind" = tiled ]; then extra=(--tile 10); else map="$map.mrfmap"; fi
    start=$(date +%s.%N)
    /usr/bin/time -f "%M" -o "$out/$engine-$kind.rss" \
      "$bin" build "$out/floor" -o "$map" --resolution 0.05 --engine "$engine" --frames "$frames" -q "${extra[@]}" >/dev/null
    secs=$(echo "$(date +%s.%N) - $start" | bc)
    acc=$("$bin" eval "$map" "$out/floor" --views "$views" --metric reference --sigma-model --json -q |
      python3 -c 'import json,sys; d=json.load(sys.stdin); print(round(d["accuracy"], 4))')
    echo "$engine $kind accuracy $acc build_s $secs peak_kb $(cat "$out/$engine-$kind.rss")"
  done
done
