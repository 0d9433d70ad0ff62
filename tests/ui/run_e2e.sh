#!/usr/bin/env bash
# End-to-end UI test in Debian's chromium (ctest labels ui;e2e). Exit 77 (skipped) without
# node, chromium or ui/node_modules. Screenshots land in ARTEFACT_DIR. CF_E2E_SCRIPT names
# another test of this folder (default e2e.mjs; e.g. e2e_resilience.mjs, which takes the
# cortexfuse CLI as a fourth argument).
set -u
daemon=${1:?usage: run_e2e.sh CORTEXFUSED UI_DIR ARTEFACT_DIR [MORE...]}; ui=${2:?}; art=${3:?}
command -v node >/dev/null 2>&1 || { echo "SKIP: node not installed"; exit 77; }
major=$(node -p 'process.versions.node.split(".")[0]')
# playwright-core is pinned to 1.61 (ui/package.json), the last to run on Debian 12's nodejs 18.
[ "$major" -ge 18 ] || { echo "SKIP: node $(node --version) is older than 18 (playwright-core)"; exit 77; }
exec node "$(dirname "$0")/${CF_E2E_SCRIPT:-e2e.mjs}" "$@"
