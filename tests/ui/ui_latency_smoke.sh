#!/usr/bin/env bash
# Smoke run of the UI latency benchmark (bench/ui_latency.sh, issue 7): one measured touch of each
# kind at 1280x800; the JSON must parse and hold, for every kind, a first and a refined picture
# (the refined one full size, not before the first), no failed touch, the renderer, the daemon's
# peak RSS and its clean exit. No timing threshold (the figures depend on the machine's load:
# docs/performance.md). Exit 77 (skipped) as the benchmark: without node >= 18, chromium or
# ui/node_modules.
# Usage: ui_latency_smoke.sh BUILD_DIR
set -u
build=${1:?usage: ui_latency_smoke.sh BUILD_DIR}
src=$(cd "$(dirname "$0")/../.." && pwd)
out=$(mktemp)
trap 'rm -f "$out"' EXIT
"$src/bench/ui_latency.sh" "$build" --quick --repeats 1 --out "$out" >/dev/null
rc=$?
[ "$rc" = 77 ] && exit 77
[ -s "$out" ] || { echo "FAIL: the benchmark wrote no JSON (exit $rc)"; exit 1; }
node - "$out" "$rc" <<'JS'
const fs = require("fs");
const [file, rc] = process.argv.slice(2);
let j;
try { j = JSON.parse(fs.readFileSync(file, "utf8")); } catch (e) { console.log(`FAIL: the output is not JSON: ${e.message}`); process.exit(1); }
const fails = [];
const check = (ok, what) => { if (!ok) fails.push(what); };
check(!j.error, `the benchmark ran (${j.error})`);
check(rc === "0", `the benchmark exited 0 (${rc})`);
check(["gl", "cpu"].includes(j.renderer), `the renderer is named (${j.renderer})`);
check(j.daemon?.peak_rss_mb > 0 && j.daemon?.exit_code === 0, `the daemon's peak RSS and clean exit (${JSON.stringify(j.daemon)})`);
check(Array.isArray(j.machine?.loadavg_start) && Array.isArray(j.machine?.loadavg_end), "the load average is reported");
check(j.sizes?.length === 1 && j.sizes[0].viewport === "1280x800", "one view size, 1280x800");
const want = ["orbit_drag", "orbit_drag_during_refine", "pinch_zoom", "preset_button", "view_button", "tf_point_drag", "opacity_slider",
              "fused_drag", "fused_pinch", "fused_camera_view", "fused_opacity_slider"];
if (j.renderer === "gl") want.push("fused_modality_toggle", "fused_modality_weight");
const kinds = j.sizes?.[0]?.kinds ?? {};
for (const k of want) {
  const v = kinds[k];
  if (!v) { fails.push(`kind ${k} measured`); continue; }
  check(v.errors === 0 && v.first_ms.n === 1 && v.refined_ms.n === 1, `${k}: one touch measured without error (${v.errors} errors)`);
  check(v.first_ms.median > 0 && v.refined_ms.median >= v.first_ms.median, `${k}: first (${v.first_ms.median} ms) then refined (${v.refined_ms.median} ms)`);
  const area = (s) => s.split("x").map(Number).reduce((a, b) => a * b, 1);
  check(/^\d+x\d+$/.test(v.first_size) && /^\d+x\d+$/.test(v.refined_size) && area(v.first_size) <= area(v.refined_size),
        `${k}: the first picture (${v.first_size}) is not larger than the refined one (${v.refined_size})`);
}
check(Array.isArray(j.over_target), "the interactions over the target are listed");
for (const s of j.sizes ?? []) for (const [k, v] of Object.entries(s.kinds)) console.log(`${s.viewport} ${k}: first ${v.first_ms.median} ms (${v.first_size}), refined ${v.refined_ms.median} ms (${v.refined_size})`);
console.log(`renderer ${j.renderer}, daemon peak RSS ${j.daemon?.peak_rss_mb} MiB, load ${j.machine?.loadavg_start} -> ${j.machine?.loadavg_end}`);
if (fails.length) { console.log("FAIL: " + fails.join("; ")); process.exit(1); }
console.log("ok");
JS
