#!/usr/bin/env bash
# Every test: the release build and the ASan+UBSan build, each through ctest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# A full disk fails a link halfway with an obscure message; say up front when space is short.
# Both trees from scratch take about 6 GB (release 1.4, ASan+UBSan 4.3; 28 Nov 2026), ccache and the UI's
# node_modules aside.
need_gb=7
avail_kb=$(df -Pk . | awk 'NR == 2 { print $4 }')
echo "run-tests: $((avail_kb / 1048576)) GB free where the builds go"
if [ "$avail_kb" -lt $((need_gb * 1048576)) ] && [ ! -d build ]; then
  echo "run-tests: warning: the two build trees need about ${need_gb} GB; a link may fail with 'No space left on device'" >&2
fi
# One job more than cores: part of every test is waiting (sockets, chromium, the simulated
# tracker's frame rate, the soak's seconds), and at -j2 on 2 cores a fifth of the CPU stood idle.
# Release ctest on this 2-vCPU VM: 886 s at -j2, 724 s at -j3 (6 Dec 2026, docs/performance.md).
jobs=$(( $(nproc) + 1 ))
bash scripts/build.sh release
ctest --test-dir build --output-on-failure -j"$jobs"
bash scripts/build.sh asan
# LeakSanitizer: TBB's and ITK's process-lifetime singletons are not leaks of ours.
# In the release half only: the .deb install test (the package is built from the release
# build, never from this one) and the tests labelled nosan, in which no C++ of ours runs (the
# UI's vitest units, systemd unit checks) or that time things (the UI latency smoke run):
# together about 4 minutes here of the command's 30-minute budget. Also the codec fuzz
# campaign (label fuzz): clang builds that binary with its own ASan+UBSan, the same binary in
# both trees, so one 30-s campaign per command is enough. And the tests named in
# tests/not_sanitized.txt, each with why: repeats of code a sibling test runs sanitized, and
# the browser resilience test. The whole-case browser test (ui_e2e) does run sanitized: it
# found a stack overflow on a connection thread.
list=tests/not_sanitized.txt
entries() { sed -n "s/^$1:[[:space:]]*\([^[:space:]#]*\).*/\1/p" "$list"; }
known=$(ctest --test-dir build-asan -N | sed -n 's/^ *Test *#[0-9]*: //p')
for name in $(entries ctest); do
  grep -qxF "$name" <<<"$known" || { echo "run-tests: $list names ctest test '$name', which ctest does not know (renamed?)" >&2; exit 1; }
done
for name in $(entries gtest); do
  grep -rqE "TEST(_F)?\\(${name%%.*}, ${name#*.}\\)" tests || { echo "run-tests: $list names gtest test '$name', which no test source defines (renamed?)" >&2; exit 1; }
done
skip_ctest=$(entries ctest | sed 's/[.]/[.]/g' | paste -sd'|')
skip_gtest=$(entries gtest | paste -sd':')
ASAN_OPTIONS=detect_leaks=0 UBSAN_OPTIONS=print_stacktrace=1 GTEST_FILTER="-$skip_gtest" \
  ctest --test-dir build-asan --output-on-failure -j"$jobs" -LE "package|nosan|fuzz" -E "^($skip_ctest)\$"
