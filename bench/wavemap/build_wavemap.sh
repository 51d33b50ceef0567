#!/usr/bin/env bash
# build_wavemap.sh WAVEMAP_SOURCE: builds wavemap's C++ library (ethz-asl/wavemap, library/cpp;
# no ROS, no FetchContent) and the driver wavemap_build.cpp next to this script.
#   WAVEMAP_SOURCE: a git dir (bare or a clone's .git) or a source tree containing library/cpp,
#   e.g. `git clone --branch v2.2.1 https://github.com/ethz-asl/wavemap /tmp/wavemap` then
#   `bench/wavemap/build_wavemap.sh /tmp/wavemap`. Measured with v2.2.1
#   (db4f2fffdc1da1bec042d51bfff58029c0c9c827).
# Env: WAVEMAP_WORK (default /tmp): sources in $WAVEMAP_WORK/wavemap-src, library build in
#   $WAVEMAP_WORK/wavemap-build, binary $WAVEMAP_WORK/wavemap-bin/wavemap_build.
# Debian 12 packages used: cmake g++ make libeigen3-dev (3.4.0) libgoogle-glog-dev (0.6.0, pulls
#   libgflags-dev) libboost-dev (1.74; wavemap only needs Boost.Preprocessor headers) libpng-dev.
# wavemap's CMake finds all three of its dependencies (Eigen, glog, Boost) on the system, so none of
# its FetchContent fallbacks run; this script stops if one would.
# Note: wavemap's CMake hard-codes -march=native; the driver is compiled with the same flags
# (required: Eigen's alignment must match the library's).
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
IN=${1:?usage: build_wavemap.sh WAVEMAP_GIT_DIR_OR_SOURCE_TREE}
WORK=${WAVEMAP_WORK:-/tmp}
SRC=$WORK/wavemap-src BUILD=$WORK/wavemap-build BIN=$WORK/wavemap-bin

pkgs="cmake g++ make pkg-config libeigen3-dev libgoogle-glog-dev libboost-dev libpng-dev"
missing=$(for p in $pkgs; do dpkg -s "$p" >/dev/null 2>&1 || echo "$p"; done)
if [ -n "$missing" ]; then
  echo "installing: $missing"
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $missing
fi

if [ -d "$IN/library/cpp" ]; then
  SRC=$IN
elif [ ! -d "$SRC/library/cpp" ]; then
  mkdir -p "$SRC"
  git --git-dir="$IN" archive HEAD | tar -x -C "$SRC"
  git --git-dir="$IN" rev-parse HEAD > "$SRC/COMMIT"
fi
echo "wavemap sources: $SRC ($(cat "$SRC/COMMIT" 2>/dev/null || echo unknown commit))"

cmake -S "$SRC/library/cpp" -B "$BUILD" -DCMAKE_BUILD_TYPE=Release -DBUILD_SHARED_LIBS=OFF \
  -DGENERATE_WAVEMAP_INSTALL_RULES=OFF | tee "$BUILD.cmake.log"
if grep -q "Fetching external" "$BUILD.cmake.log"; then
  echo "wavemap's CMake wants to download a dependency (see above); install it from Debian" >&2
  exit 1
fi
cmake --build "$BUILD" -j"$(nproc)" --target wavemap_core wavemap_io

mkdir -p "$BIN"
g++ -std=c++17 -O3 -DNDEBUG -march=native -DEIGEN_INITIALIZE_MATRICES_BY_NAN \
  -I"$SRC/library/cpp/include" -isystem /usr/include/eigen3 \
  "$HERE/wavemap_build.cpp" -o "$BIN/wavemap_build" \
  "$BUILD/src/io/libwavemap_io.a" "$BUILD/src/core/libwavemap_core.a" \
  -lglog -lgflags -lpng -lpthread
echo "built $BIN/wavemap_build"
