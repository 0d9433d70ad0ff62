#!/usr/bin/env bash
# cortexfuse sim tracker on a pty and cortexfuse track against it (one JSON line per frame);
# bad inputs give a one-line error and a non-zero exit.
set -euo pipefail
CF="$1"
DATA="$2"
tmp=$(mktemp -d)
sim=""
cleanup() {
  if [ -n "$sim" ]; then kill "$sim" 2>/dev/null || true; wait "$sim" 2>/dev/null || true; fi
  rm -rf "$tmp"
}
trap cleanup EXIT
fail() { echo "FAIL: $*" >&2; exit 1; }

"$CF" sim tracker --pty --link "$tmp/polaris" --camera --duration-s 60 \
  --faults bit_flip=0.05,garbage=0.05,truncate=0.03,tool_missing=0.1 > "$tmp/sim.out" 2> "$tmp/sim.err" &
sim=$!
for _ in $(seq 100); do [ -s "$tmp/sim.out" ] && break; sleep 0.1; done
[ "$(head -1 "$tmp/sim.out")" = "$tmp/polaris" ] || fail "the simulator did not print its link"

"$CF" track --serial "$tmp/polaris" --rom "$DATA/roms/cf_reference.rom" --rom "$DATA/roms/cf_pointer.rom" \
  --rom "$DATA/roms/cf_camera.rom" --frames 30 --json > "$tmp/frames.jsonl" 2> "$tmp/track.err" || fail "track: $(cat "$tmp/track.err")"
n=$(grep -c '"frame":' "$tmp/frames.jsonl")
[ "$n" = 30 ] || fail "expected 30 JSON frames, got $n"
grep -q '"name":"cf_pointer"' "$tmp/frames.jsonl" || fail "no cf_pointer in the frames"
grep -q '"t_mm":\[' "$tmp/frames.jsonl" || fail "no pose in any frame"
grep -q '"state":"stopped"' "$tmp/track.err" || fail "no status line: $(cat "$tmp/track.err")"

# The same over TCP (loopback, an ephemeral port printed by the simulator).
"$CF" sim tracker --tcp 127.0.0.1:0 --duration-s 60 > "$tmp/simtcp.out" 2>/dev/null &
simtcp=$!
for _ in $(seq 100); do [ -s "$tmp/simtcp.out" ] && break; sleep 0.1; done
port=$(sed -n 's/^tcp 127.0.0.1:\([0-9]*\)$/\1/p' "$tmp/simtcp.out")
[ -n "$port" ] || { kill "$simtcp" 2>/dev/null || true; fail "the TCP simulator did not print its port"; }
"$CF" track --tcp "127.0.0.1:$port" --rom "$DATA/roms/cf_pointer.rom" --frames 10 --json > "$tmp/tcp.jsonl" 2>/dev/null || { kill "$simtcp" 2>/dev/null || true; fail "track over TCP"; }
kill "$simtcp" 2>/dev/null || true; wait "$simtcp" 2>/dev/null || true
[ "$(grep -c '"frame":' "$tmp/tcp.jsonl")" = 10 ] || fail "expected 10 frames over TCP"

# Bad inputs: one line naming the input, exit 1.
expect_error() {  # pattern, command...
  local pat="$1"; shift
  if "$@" > /dev/null 2> "$tmp/err"; then fail "accepted: $*"; fi
  grep -q "$pat" "$tmp/err" || fail "'$*' said: $(cat "$tmp/err")"
}
expect_error "not_a_rom.rom: not an NDI tool definition" "$CF" track --serial "$tmp/polaris" --rom "$DATA/roms/not_a_rom.rom" --frames 1
[ "$(wc -l < "$tmp/err")" = 1 ] || fail "more than one line: $(cat "$tmp/err")"
expect_error "missing.rom: cannot open" "$CF" track --serial "$tmp/polaris" --rom "$tmp/missing.rom" --frames 1
expect_error "expected HOST:PORT" "$CF" track --tcp localhost --frames 1
expect_error "baud 19200" "$CF" track --serial "$tmp/polaris" --baud 19200 --frames 1
expect_error "serial $tmp/nonexistent: cannot open" "$CF" track --serial "$tmp/nonexistent" --frames 1 --timeout-s 1
expect_error "must be 20, 60 or 250" "$CF" sim tracker --pty --rate 30 --duration-s 1
expect_error "unknown fault name" "$CF" sim tracker --pty --faults bogus=1 --duration-s 1

# The simulator stops on SIGTERM and reports its faults.
kill -TERM "$sim"; wait "$sim" || fail "simulator exit status"
sim=""
grep -q '"faults"' "$tmp/sim.err" || fail "no fault summary: $(cat "$tmp/sim.err")"
echo "ok"
