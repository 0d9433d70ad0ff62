#!/usr/bin/env bash
# The UI's vitest unit tests (ctest label ui). Exit 77 (skipped) without npm or without
# ui/node_modules (scripts/build.sh runs npm ci); fails when the UI build left no ui/dist.
set -u
ui=${1:?usage: run_unit.sh UI_DIR}
command -v npm >/dev/null 2>&1 || { echo "SKIP: npm not installed"; exit 77; }
[ -d "$ui/node_modules" ] || { echo "SKIP: $ui/node_modules missing (scripts/build.sh runs npm ci)"; exit 77; }
cd "$ui" || exit 1
npm test --silent -- --reporter=verbose 2>&1
rc=$?
if [ ! -f dist/index.html ]; then
  echo "FAIL: $ui/dist/index.html missing: the UI build (npm run build) failed or did not run"
  exit 1
fi
exit $rc
