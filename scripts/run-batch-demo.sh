#!/usr/bin/env bash
# The batch demo: generate phantom cases from the bundled real MRI, register each from random
# initial misalignments, print the evaluation table (also: scripts/run-demo.sh --batch).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/build.sh release
out=out/demo
rm -rf "$out"
./build/cli/cortexfuse phantom "$out/cases" --n 4 --seed 1 --quiet
./build/cli/cortexfuse evaluate "$out/cases" --trials 10 --json "$out/evaluation.json" --md "$out/evaluation.md" \
  --png "$out/evaluation.png"
echo "demo: cases in $out/cases, table in $out/evaluation.md, picture in $out/evaluation.png" >&2
