#!/usr/bin/env bash
# systemd-analyze verify on systemd/cortexfused.service, with ExecStart pointed at the built
# binary (the installed path does not exist in a build tree). Exit 77 (skipped) without systemd.
set -euo pipefail
unit=$1 binary=$2
command -v systemd-analyze >/dev/null 2>&1 || { echo "systemd-analyze not installed: skipped"; exit 77; }
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
sed "s|^ExecStart=/usr/bin/cortexfused|ExecStart=$binary|" "$unit" > "$tmp/cortexfused.service"
grep -q "^ExecStart=$binary" "$tmp/cortexfused.service"
out=$(systemd-analyze verify "$tmp/cortexfused.service" 2>&1) || { echo "$out"; exit 1; }
# verify exits 0 on some warnings; any line naming the unit is a problem.
if echo "$out" | grep -q "cortexfused.service"; then echo "$out"; exit 1; fi
# The tracker's priorities (docs/tracker.md): SCHED_FIFO allowed, the one capability granted.
for key in Type=notify WatchdogSec= DynamicUser=yes ProtectSystem=strict StateDirectory= DevicePolicy=closed \
           RestrictRealtime=no LimitRTPRIO= AmbientCapabilities=CAP_SYS_NICE "RestartPreventExitStatus=69 2"; do
  grep -q "^$key" "$unit" || { echo "$unit: $key missing"; exit 1; }
done
echo "ok"
