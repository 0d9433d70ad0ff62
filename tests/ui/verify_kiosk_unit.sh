#!/usr/bin/env bash
# systemd-analyze verify on systemd/cortexfuse-kiosk.service (and systemd-sysusers --dry-run on
# its sysusers.d file), plus the promises docs/ui.md makes about it. Where cage is not installed
# (it is needed on the cart only) ExecStart's /usr/bin/cage is pointed at a stand-in executable
# so verify can check the rest. Exit 77 (skipped) without systemd-analyze.
set -euo pipefail
unit=${1:?usage: verify_kiosk_unit.sh UNIT SYSUSERS_CONF}; sysusers=${2:?}
command -v systemd-analyze >/dev/null 2>&1 || { echo "systemd-analyze not installed: skipped"; exit 77; }
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
name=$(basename "$unit")
cage=/usr/bin/cage
if [ ! -x "$cage" ]; then
  cage="$tmp/cage"; printf '#!/bin/sh\nexit 0\n' > "$cage"; chmod +x "$cage"
fi
sed "s|^ExecStart=/usr/bin/cage |ExecStart=$cage |" "$unit" > "$tmp/$name"
grep -q "^ExecStart=$cage " "$tmp/$name" || { echo "$unit: ExecStart does not start /usr/bin/cage"; exit 1; }
out=$(systemd-analyze verify "$tmp/$name" 2>&1) || { echo "$out"; exit 1; }
# verify exits 0 on some warnings; any line naming the unit is a problem.
if echo "$out" | grep -q "$name"; then echo "$out"; exit 1; fi
# What it must do (issue 7, docs/ui.md): chromium in kiosk mode under cage, at the daemon's
# loopback address, after the daemon, restarted if it dies, on a seat session.
for re in '^After=cortexfused\.service' '^Wants=cortexfused\.service' '^Restart=always' '^PAMName=' '^TTYPath=/dev/tty1' \
          '^User=cortexfuse-kiosk' '/usr/bin/chromium --kiosk' '^Environment=CORTEXFUSE_KIOSK_URL=http://127\.0\.0\.1:8080/$' \
          '^ExecStartPre=\+/usr/bin/systemd-sysusers /usr/lib/sysusers\.d/cortexfuse-kiosk\.conf' '^WantedBy=graphical\.target'; do
  grep -Eq -- "$re" "$unit" || { echo "$unit: no line matching $re"; exit 1; }
done
grep -q -- '--disable-pinch' "$unit" || { echo "$unit: chromium may pinch-zoom the kiosk"; exit 1; }
if command -v systemd-sysusers >/dev/null 2>&1; then
  # --root: a scratch root, so nothing on this machine is touched; it must parse and create the user.
  mkdir -p "$tmp/root/etc" "$tmp/root/usr/lib/sysusers.d"
  printf 'root:x:0:0::/root:/bin/sh\n' > "$tmp/root/etc/passwd"
  printf 'root:x:0:\nvideo:x:44:\nrender:x:105:\ninput:x:104:\n' > "$tmp/root/etc/group"
  : > "$tmp/root/etc/shadow"; : > "$tmp/root/etc/gshadow"
  cp "$sysusers" "$tmp/root/usr/lib/sysusers.d/cortexfuse-kiosk.conf"
  out=$(systemd-sysusers --root="$tmp/root" 2>&1) || { echo "$sysusers: $out"; exit 1; }
  grep -q '^cortexfuse-kiosk:' "$tmp/root/etc/passwd" || { echo "$sysusers: no cortexfuse-kiosk user made ($out)"; exit 1; }
  for g in video render input; do
    grep -Eq "^$g:x:[0-9]+:.*cortexfuse-kiosk" "$tmp/root/etc/group" || { echo "$sysusers: cortexfuse-kiosk not in group $g"; exit 1; }
  done
fi
echo "ok"
