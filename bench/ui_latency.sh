#!/usr/bin/env bash
# UI latency benchmark (issue 7): how soon a touch that changes the view shows a new picture,
# per kind of touch, in Debian's chromium against cortexfused (bench/ui_latency.mjs; JSON on
# stdout, log on stderr). Needs node >= 18, ui/node_modules (npm ci), ui/dist (npm run build)
# and /usr/bin/chromium; exits 77 (skipped) without them.
# Usage: bench/ui_latency.sh BUILD_DIR [--repeats 10] [--sizes 1280x800,1920x1080]
#                           [--renderer auto|gl|cpu] [--quick] [--kinds a,b] [--out FILE] [--shots DIR]
#   e.g. bench/ui_latency.sh build --out ui_latency.json
set -u
here=$(cd "$(dirname "$0")" && pwd)
build=${1:?usage: ui_latency.sh BUILD_DIR [options]}; shift
daemon="$build/daemon/cortexfused"
[ -x "$daemon" ] || { echo "FAIL: $daemon: no daemon binary (ninja -C $build cortexfused)" >&2; exit 1; }
command -v node >/dev/null 2>&1 || { echo "SKIP: node not installed"; exit 77; }
major=$(node -p 'process.versions.node.split(".")[0]')
[ "$major" -ge 18 ] || { echo "SKIP: node $(node --version) is older than 18 (playwright-core 1.61)"; exit 77; }
exec node "$here/ui_latency.mjs" --daemon "$daemon" --ui "$here/../ui" "$@"
