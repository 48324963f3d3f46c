#!/usr/bin/env bash
# Ray throughput and whole-render speed-up: runs dtraced-bench-rays (src/bench/bench_rays.cpp) on
# both scenes (100,000 spheres; about 1M triangles) with the protocol written at the top of
# bench_rays.cpp (one warm-up, median and min-max of RUNS runs, one thread by
# thread CPU time and all threads by wall time), then the whole-render benchmark (scenes/showcase.json
# at 1920x1080, 16 spp, scalar vs best isa). A benchmark, not a test: it prints tables and marks the
# issue's targets MET or MISSED, and fails only when it cannot run.
#
# Usage, after the README's build (cmake -B build && cmake --build build):
#   tests/bench/ray_throughput.sh            # the full run (several minutes on 2 cores)
#   tests/bench/ray_throughput.sh --quick    # a smoke run in seconds
# Any argument is passed on to dtraced-bench-rays (see its --help), e.g. --scene mesh --isa scalar,avx2.
# Environment: DTRACED_BENCH_RAYS (binary; default build/src/bench/dtraced-bench-rays), RUNS (5),
# CSV (a file to write every figure to; default none), RENDER=0 to skip the whole renders.
# Embree is compared when the build found libembree-dev (CMake option DTRACED_BENCH_EMBREE).
# On a shared machine the 1-thread figures (CPU time) are the ones to trust; the all-threads ones
# are wall time and move with whatever else runs.
set -euo pipefail

root=$(cd "$(dirname "$0")/../.." && pwd)
BIN=${DTRACED_BENCH_RAYS:-$root/build/src/bench/dtraced-bench-rays}
RUNS=${RUNS:-5}
RENDER=${RENDER:-1}
CSV=${CSV:-}

if [[ ! -x $BIN ]]; then
  echo "ray_throughput.sh: $BIN not found; build first (cmake --build build --target dtraced-bench-rays)" >&2
  exit 1
fi
args=(--runs "$RUNS" --render-scene "$root/scenes/showcase.json")
[[ $RENDER == 1 ]] && args+=(--render)
[[ -n $CSV ]] && args+=(--csv "$CSV")
echo "# $(uname -srm); $(nproc) CPUs; load $(cut -d' ' -f1-3 /proc/loadavg)"
exec "$BIN" "${args[@]}" "$@"
