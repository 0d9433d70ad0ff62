#!/usr/bin/env bash
# The main job: set up, build, and run the appliance's daemon, cortexfused, in the foreground
# with its embedded defaults: the simulated NDI Polaris (through the real driver over a pty),
# the simulated camera, the bundled MRI (data/), a phantom case generated at start. The web UI
# and the API answer at http://127.0.0.1:8080/ (CF_LISTEN=HOST:PORT to change it). Ctrl-C stops
# it cleanly.
#   scripts/run-demo.sh --batch   the batch demo instead (phantom cases + evaluation table;
#                                 also scripts/run-batch-demo.sh)
set -euo pipefail
cd "$(dirname "$0")/.."
if [ "${1:-}" = "--batch" ]; then
  exec bash scripts/run-batch-demo.sh
fi
bash scripts/setup.sh
bash scripts/build.sh release
listen=${CF_LISTEN:-127.0.0.1:8080}
state=out/daemon
mkdir -p "$state"
host=${listen%:*}
port=${listen##*:}
cat >&2 <<MSG

  CortexFuse is starting: open the UI at  http://$host:$port/
  (API: http://$host:$port/api/status, push channel ws://$host:$port/api/ws;
   state in $state; Ctrl-C stops it)

MSG
exec ./build/daemon/cortexfused --listen "$listen" --state-dir "$state"
