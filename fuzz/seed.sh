#!/usr/bin/env bash
# Seeds each fuzz target's corpus with one valid input, made by the mrfmap command from a
# tiny simulated scene (and a CARMEN log written here), so the fuzzers start from files
# that parse.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/.." && pwd)
cargo build --release --manifest-path "$root/Cargo.toml" -p mrfmap-cli -q
m="$root/target/release/mrfmap"
tmp=$(mktemp -d)
cat > "$tmp/scene.toml" <<'TOML'
[camera]
fx = 20.0
fy = 20.0
cx = 7.5
cy = 5.5
width = 16
height = 12
depth_scale = 5000.0
[noise]
bias = [0.0, 0.0, 0.002]
std = [0.002, 0.0, 0.002]
[[box]]
min = [-1.0, -1.0, -0.1]
max = [1.0, 1.0, 0.0]
[orbit]
center = [0.0, 0.0, 0.0]
radius = 1.0
height = 0.8
views = 2
TOML
"$m" -q simulate "$tmp/scene.toml" "$tmp/data" >/dev/null
"$m" -q build "$tmp/data" -o "$tmp/m.mrfmap" --resolution 0.1 >/dev/null
"$m" -q build "$tmp/data" -o "$tmp/tiles" --resolution 0.1 --tile 0.8 >/dev/null
"$m" -q export "$tmp/m.mrfmap" --ply "$tmp/m.ply" --bt "$tmp/m.bt" --ot "$tmp/m.ot" >/dev/null
printf 'FLASER 3 1.0 2.0 81.83 0.5 0.5 0.1 0 0 0 1.0 h 1.0\nODOM 0 0 0 0 0 0 1 h 1\n' > "$tmp/log"
seed() { mkdir -p "$here/corpus/$1"; cp "$2" "$here/corpus/$1/seed-$(basename "$2")"; }
seed depth_png "$tmp/data/depth/000000.png"
seed camera_toml "$tmp/data/camera.toml"
seed noise_toml "$tmp/data/noise.toml"
seed scene_toml "$tmp/scene.toml"
seed tile_index "$tmp/tiles/tiles.toml"
seed map_file "$tmp/m.mrfmap"
seed ply "$tmp/m.ply"
seed octomap "$tmp/m.bt"
seed octomap "$tmp/m.ot"
seed carmen "$tmp/log"
rm -rf "$tmp"
