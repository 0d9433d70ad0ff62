#!/usr/bin/env bash
# Builds the portable .deb (issue 6, docs/packaging.md): a build folder of its own configured with
# -DCF_NATIVE=OFF -DCF_MARCH=<baseline> (the developer/test build keeps -march=native), only the
# two binaries and the default configuration, then cpack. A package made from a -march=native
# build runs only on CPUs like the build machine's; the binaries of this one run on any x86-64
# CPU with the baseline, and refuse to start elsewhere with one line (exit 69).
# Usage: [CF_MARCH=x86-64-v3] [JOBS=2] scripts/build-package.sh [BUILD_DIR [OUT_DIR]]
#   BUILD_DIR default build-package, OUT_DIR default BUILD_DIR/deb. Prints the .deb's path last.
set -euo pipefail
cd "$(dirname "$0")/.."
build=${1:-build-package}
out=${2:-$build/deb}
march=${CF_MARCH:-x86-64-v3}
jobs=${JOBS:-$(nproc)}
case "$march" in
  native) echo "build-package: CF_MARCH=native would make a package for this machine only; name a baseline (x86-64-v2, x86-64-v3)" >&2; exit 2 ;;
esac
launcher=()
if command -v ccache >/dev/null 2>&1; then
  export CCACHE_BASEDIR="$PWD" CCACHE_NOHASHDIR=true
  launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache -DCMAKE_C_COMPILER_LAUNCHER=ccache)
fi
cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCF_NATIVE=OFF -DCF_SANITIZE=OFF \
      "-DCF_MARCH=$march" -DCF_BUILD_TESTS=OFF -DCMAKE_SKIP_INSTALL_ALL_DEPENDENCY=ON "${launcher[@]}" >/dev/null
ninja -C "$build" -j"$jobs" cortexfused cortexfuse cf_package_config
[ -f ui/dist/index.html ] || echo "build-package: ui/dist not built (scripts/build.sh builds it): the package has no UI" >&2
mkdir -p "$out"
out=$(realpath "$out")
(cd "$build" && cpack -G DEB -B "$out" >/dev/null)
deb=$(ls -t "$out"/cortexfuse_*.deb | head -1)
echo "build-package: $deb (CPU baseline $march)"
echo "$deb"
