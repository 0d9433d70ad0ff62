#!/bin/bash
# Smoke run of the daemon load benchmark (issue 6): a short window, then the JSON must parse and
# show requests served with no error, tracker frames received in order with no gap, and the
# daemon stopped cleanly. No timing assertion (latency, and frames the device's link missed
# under load, depend on the machine's load).
# Usage: daemon_load_smoke.sh BENCH_EXE [SECONDS]
set -euo pipefail
exe=$1
secs=${2:-10}
command -v jq >/dev/null || { echo "jq not installed: skipped"; exit 77; }
out=$(mktemp)
trap 'rm -f "$out"' EXIT
rc=0
"$exe" --seconds "$secs" --clients 20 >"$out" || rc=$?
cat "$out"
jq -e . "$out" >/dev/null || { echo "FAIL: the output is not JSON"; exit 1; }
check() {  # check JQ_EXPR WHAT
    if ! jq -e "$1" "$out" >/dev/null; then echo "FAIL: $2 ($1)"; exit 1; fi
}
check '.requests > 0' "requests were served"
check '.errors == 0' "no request failed"
check '.tracker.frames_in_window > 0' "tracker frames arrived over the WebSocket"
check '.tracker.seq_gaps == 0 and .tracker.seq_out_of_order == 0 and .tracker.frame_out_of_order == 0' "frames in order without gaps"
check '.tracker.websocket_closed_early == false' "the WebSocket stayed open"
check '.registration.ran == true and (.registration.state | IN("running", "succeeded"))' "the registration ran"
check '(.latency_ms.p50 > 0) and (.latency_ms.p99 >= .latency_ms.p50) and (.daemon.peak_rss_mb > 0)' "figures are filled in"
check '.daemon.exit_code == 0' "cortexfused exited 0 on SIGTERM"
if [ "$rc" != 0 ]; then
    # The benchmark also fails a run on a gap in the device's frame numbers (issue 6's figure: the
    # serial link under load, measured by its --runs). That is timing, not function: a sanitizer
    # build on a busy machine can miss a frame of the simulator now and then (1 in 600 seen). The
    # functional checks above passed, so such a run passes here, with the figure said.
    if jq -e '.summary.gaps > 0 and .errors == 0 and .tracker.seq_gaps == 0 and .issue6_checks.no_error' "$out" >/dev/null; then
        echo "note: $(jq -r '.summary.frames_missed' "$out") device frame(s) missed in $(jq -r '.summary.gaps' "$out") gap(s): timing under load, not a failure of this smoke run"
    else
        echo "FAIL: the benchmark exited $rc"
        exit 1
    fi
fi
echo "ok"
