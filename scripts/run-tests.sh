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
bash scripts/build.sh release
ctest --test-dir build --output-on-failure -j2
bash scripts/build.sh asan
# LeakSanitizer: TBB's and ITK's process-lifetime singletons are not leaks of ours.
# In the release half only: the .deb install test (the package is built from the release
# build, never from this one) and the tests labelled nosan, in which no C++ of ours runs (the
# UI's vitest units, systemd unit checks) or that time things (the UI latency smoke run):
# together about 4 minutes here of the command's 30-minute budget. Also the codec fuzz
# campaign (label fuzz): clang builds that binary with its own ASan+UBSan, the same binary in
# both trees, so one 30-s campaign per command is enough. And the browser resilience test
# (~75 s there): daemon and chromium restarts, a dropped tracker; the daemon code it reaches
# runs sanitized in the daemon test programs (drafts, navigation, case data). The whole-case
# browser test (ui_e2e) does run sanitized: it found a stack overflow on a connection thread.
ASAN_OPTIONS=detect_leaks=0 UBSAN_OPTIONS=print_stacktrace=1 \
  ctest --test-dir build-asan --output-on-failure -j2 -LE "package|nosan|fuzz" -E "^ui_e2e_resilience$"
