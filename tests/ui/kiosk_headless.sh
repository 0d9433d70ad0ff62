#!/usr/bin/env bash
# The kiosk unit's own command (systemd/cortexfuse-kiosk.service ExecStart: cage, then chromium
# in kiosk mode) run for real on wlroots' headless backend, against a cortexfused started here:
# the browser under cage loads the UI and its script connects the push channel (the daemon
# lists it in /api/status), a screenshot of cage's output is saved (grim), and when chromium
# dies cage exits with it, which is what makes systemd's Restart=always start the kiosk again.
# What this cannot show: a DRM screen, a touchscreen, logind's seat (the unit's PAMName/TTY lines).
# Usage: kiosk_headless.sh UNIT CORTEXFUSED ARTEFACT_DIR. Exit 77 (skipped) without cage, grim or
# chromium (scripts/setup.sh installs them).
set -euo pipefail
unit=${1:?usage: kiosk_headless.sh UNIT CORTEXFUSED ARTEFACT_DIR}; daemon=${2:?}; art=${3:?}
for exe in /usr/bin/cage /usr/bin/chromium /usr/bin/grim; do
  [ -x "$exe" ] || { echo "SKIP: $exe not installed (scripts/setup.sh installs it)"; exit 77; }
done
mkdir -p "$art"
tmp=$(mktemp -d)
chmod 755 "$tmp"
pids=()
cleanup() {
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  sleep 0.5
  for p in "${pids[@]}"; do kill -9 "$p" 2>/dev/null || true; done
  rm -rf "$tmp"
}
trap cleanup EXIT

# cage refuses to run as root (it drops privileges it could not get back): as root, the kiosk
# runs as nobody, as the unit runs it as its own unprivileged user.
as_user=()
if [ "$(id -u)" = 0 ]; then
  command -v runuser >/dev/null || { echo "SKIP: runuser missing"; exit 77; }
  as_user=(runuser -u nobody --)
  owner=nobody
else
  owner=$(id -un)
fi

port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
"$daemon" --listen "127.0.0.1:$port" --state-dir "$tmp/state" >"$tmp/daemon.log" 2>&1 &
pids+=($!)
for _ in $(seq 1 300); do curl -fs "http://127.0.0.1:$port/api/status" >/dev/null 2>&1 && break; sleep 0.1; done
curl -fs "http://127.0.0.1:$port/api/status" >/dev/null || { echo "FAIL: cortexfused did not answer"; tail -20 "$tmp/daemon.log"; exit 1; }

# ExecStart as systemd would run it: continuation lines joined, ${CORTEXFUSE_KIOSK_URL} this
# daemon's address, the profile folder a scratch one the kiosk user may write.
cmd=$(sed -n '/^ExecStart=/,/[^\\]$/p' "$unit" | sed 's/\\$//' | tr '\n' ' ' | sed 's/^ExecStart=//')
grep -q -- '--user-data-dir=/var/lib/cortexfuse-kiosk/chromium' <<<"$cmd" || { echo "FAIL: $unit: ExecStart has no --user-data-dir=/var/lib/cortexfuse-kiosk/chromium"; exit 1; }
mkdir -p "$tmp/profile" "$tmp/run" "$tmp/home"
chmod 700 "$tmp/run"
chown -R "$owner" "$tmp/profile" "$tmp/run" "$tmp/home"
cmd=${cmd//'${CORTEXFUSE_KIOSK_URL}'/http://127.0.0.1:$port/}
cmd=${cmd//--user-data-dir=\/var\/lib\/cortexfuse-kiosk\/chromium/--user-data-dir=$tmp/profile}
read -r -a argv <<<"$cmd"
[ "${argv[0]}" = /usr/bin/cage ] || { echo "FAIL: ExecStart does not start /usr/bin/cage: ${argv[0]}"; exit 1; }
# Headless output, software renderer, no input devices: the parts a CI machine lacks.
"${as_user[@]}" env -i PATH=/usr/bin:/bin HOME="$tmp/home" XDG_RUNTIME_DIR="$tmp/run" XDG_SESSION_TYPE=wayland \
  WLR_BACKENDS=headless WLR_RENDERER=pixman WLR_LIBINPUT_NO_DEVICES=1 "${argv[@]}" >"$tmp/cage.log" 2>&1 &
cage_pid=$!
pids+=("$cage_pid")

# The UI's script opens the push channel once it has loaded and asked for the status.
connected=""
deadline=$((SECONDS + 60))
while [ "$SECONDS" -lt "$deadline" ]; do
  if ! kill -0 "$cage_pid" 2>/dev/null; then echo "FAIL: cage exited early"; grep -v "Basic output test" "$tmp/cage.log" | tail -20; exit 1; fi
  n=$(curl -fs "http://127.0.0.1:$port/api/status" | jq '.modules.http.websocket_clients | length')
  if [ "${n:-0}" -ge 1 ]; then connected=1; break; fi
  sleep 0.2
done
[ -n "$connected" ] || { echo "FAIL: the kiosk browser did not connect the UI's push channel within 60 s"; grep -v "Basic output test" "$tmp/cage.log" | tail -20; exit 1; }
sleep 2  # the first picture
# A picture to look at, not a check: on the headless backend cage repaints only what changed
# into the buffer grim copies, and chromium gets no window size from it there (the window stays
# ~530x130 at the top left, also with a plain page). Whether either happens on a DRM screen
# cannot be checked here.
"${as_user[@]}" env XDG_RUNTIME_DIR="$tmp/run" WAYLAND_DISPLAY=wayland-0 grim "$tmp/run/shot.png" && cp "$tmp/run/shot.png" "$art/kiosk-headless.png"

# chromium dies: cage must end with it (then systemd restarts the unit).
pkill -KILL -f -- "--user-data-dir=$tmp/profile" || { echo "FAIL: no chromium process with the kiosk profile"; exit 1; }
for _ in $(seq 1 100); do kill -0 "$cage_pid" 2>/dev/null || break; sleep 0.1; done
if kill -0 "$cage_pid" 2>/dev/null; then echo "FAIL: cage still runs 10 s after chromium died: systemd would not restart the kiosk"; exit 1; fi
echo "ok: the unit's ExecStart ran chromium --kiosk under cage; the UI connected; cage ended with chromium"
