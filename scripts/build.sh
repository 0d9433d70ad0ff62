#!/usr/bin/env bash
# Configures and builds. Usage: scripts/build.sh [release|asan]  (default release)
set -euo pipefail
cd "$(dirname "$0")/.."
kind=${1:-release}
launcher=()
if command -v ccache >/dev/null 2>&1; then
  # Paths relative to the checkout, so a fresh clone elsewhere reuses what an earlier build
  # compiled (CI builds twice a run, on the same machine run after run).
  export CCACHE_BASEDIR="$PWD" CCACHE_NOHASHDIR=true
  launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache -DCMAKE_C_COMPILER_LAUNCHER=ccache)
fi
case "$kind" in
  release) cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo "${launcher[@]}" >/dev/null ;;
  asan)    cmake -S . -B build-asan -G Ninja -DCMAKE_BUILD_TYPE=Debug -DCF_SANITIZE=ON "${launcher[@]}" >/dev/null ;;
  *) echo "usage: $0 [release|asan]" >&2; exit 2 ;;
esac
dir=build; [ "$kind" = asan ] && dir=build-asan
ninja -C "$dir" -j"$(nproc)"

# The web UI (ui/, served by cortexfused at /): npm ci when the lock file changed or
# node_modules is missing, then npm run build into ui/dist. A failed UI build does not fail the
# C++ build; it removes ui/dist so the UI tests (ctest -L ui) fail and say so.
if command -v npm >/dev/null 2>&1; then
  (
    cd ui || exit 1
    stamp=node_modules/.cf-lock.sha256
    want=$(sha256sum package-lock.json | cut -d' ' -f1)
    if [ ! -d node_modules ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
      npm ci --no-audit --no-fund || exit 1
      echo "$want" > "$stamp"
    fi
    npm run build || exit 1
  ) || { echo "build: the web UI build failed (ui/); the UI tests will fail" >&2; rm -rf ui/dist; }
else
  echo "build: npm not found, the web UI (ui/) is not built (scripts/setup.sh installs it)" >&2
fi
