#!/usr/bin/env bash
# End-to-end UI test in Debian's chromium (ctest labels ui;e2e). Exit 77 (skipped) without
# node, chromium or ui/node_modules. Screenshots land in ARTEFACT_DIR.
set -u
daemon=${1:?usage: run_e2e.sh CORTEXFUSED UI_DIR ARTEFACT_DIR}; ui=${2:?}; art=${3:?}
command -v node >/dev/null 2>&1 || { echo "SKIP: node not installed"; exit 77; }
exec node "$(dirname "$0")/e2e.mjs" "$daemon" "$ui" "$art"
