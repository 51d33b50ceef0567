#!/usr/bin/env bash
# Fuzzes every parser (or TARGETS) for SECONDS each (default 60: a short pass), one after another, on
# stable Rust: libFuzzer's coverage comes from stable -C flags; safe Rust needs no sanitizer.
# A finding (panic, timeout over 10 s, allocation over 1 GiB) stops that target and leaves
# the input in fuzz/artifacts/TARGET/; add it as a regression test and fix it.
#
# usage: fuzz/run.sh [SECONDS] [TARGETS...]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
secs=${1:-60}
shift || true
all="depth_png camera_toml noise_toml scene_toml tile_index map_file ply octomap carmen bag_messages"
targets=${*:-$all}
for t in $targets; do
  case " $all " in *" $t "*) ;; *) echo "no fuzz target $t; the targets: $all" >&2; exit 2 ;; esac
done
"$here/seed.sh"
flags="-Cpasses=sancov-module -Cllvm-args=-sanitizer-coverage-level=4 \
 -Cllvm-args=-sanitizer-coverage-inline-8bit-counters -Cllvm-args=-sanitizer-coverage-pc-table \
 -Cllvm-args=-sanitizer-coverage-trace-compares --cfg fuzzing -Cdebug-assertions -Coverflow-checks"
# An explicit --target keeps the instrumentation off build scripts and proc macros.
triple=$(rustc -vV | sed -n 's/^host: //p')
RUSTFLAGS="$flags" cargo build --release --manifest-path "$here/Cargo.toml" --target-dir "$here/target" --target "$triple" --bins
for t in $targets; do
  mkdir -p "$here/corpus/$t" "$here/artifacts/$t"
  echo "== $t: $secs s"
  "$here/target/$triple/release/$t" "$here/corpus/$t" -max_total_time="$secs" -timeout=10 -rss_limit_mb=2048 \
    -malloc_limit_mb=1024 -artifact_prefix="$here/artifacts/$t/" -print_final_stats=1 2>&1 \
    | grep -E "^(#[0-9]+.*DONE|stat::number_of_executed_units|stat::peak_rss_mb|==|SUMMARY|.*panicked|.*deadly)" || true
done
