#!/bin/bash
# Rigid co-registration, ours (ITK v4) beside elastix, on the same synthetic CT-like cases
# with known truth (a real T1 moved, put on a CT-like grid, intensities remapped).
# Prints one JSON object: per case and median seconds, mean/max error over the brain (mm),
# peak RSS (MB) of each tool.
#   bench/coregister_vs_elastix.sh [T1] [BRAIN_MASK] [N_CASES] [BUILD_DIR]
# REPEATS=k (environment, default 1) runs every case k times per tool, alternating the tools
# (ours, elastix, ours, ...) so that the machine's load falls on both alike; errors are measured on
# every run.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(dirname "$here")
t1=${1:-$root/data/t1_head_mne_ecog.nii.gz}
mask=${2:-$root/data/brainmask_mne_ecog_binary.nii.gz}
n=${3:-3}
build=${4:-$root/build}
cf=$build/cli/cortexfuse
command -v elastix >/dev/null || { echo "elastix not installed (apt-get install elastix)" >&2; exit 1; }
[ -x "$cf" ] || { echo "no $cf: build first" >&2; exit 1; }
work=$(mktemp -d /tmp/cf_coreg_bench.XXXXXX)
trap 'rm -rf "$work"' EXIT
"$cf" coregister-synth "$t1" --out "$work" --n "$n" --seed 7 > "$work/cases.json"
threads=$(nproc)
repeats=${REPEATS:-1}
load_start=$(cut -d' ' -f1 /proc/loadavg)
results="["
for c in "$work"/case_*; do
for rep in $(seq 1 "$repeats"); do
  # Ours (Mattes, default schedule), then elastix; each timed with its peak RSS. (Ours with
  # --metric nmi, ITK's joint-histogram MI, fails on this CT-like case: see docs/planning.md.)
  for tool in ours_mattes elastix; do
    out="$c/$tool.$rep"; mkdir -p "$out"
    case $tool in
      ours_mattes) cmd=("$cf" coregister "$t1" "$c/moving.nii.gz" --out "$out/T.tfm" --metric mattes --json);;
      elastix)     cmd=(elastix -f "$t1" -m "$c/moving.nii.gz" -p "$here/elastix_rigid_mi.txt" -out "$out" -threads "$threads");;
    esac
    start=$(date +%s.%N)
    /usr/bin/time -f "%M" -o "$out/rss_kb" "${cmd[@]}" > "$out/log" 2>&1 || { echo "$tool failed on $c, see $out/log" >&2; cat "$out/log" >&2; exit 1; }
    end=$(date +%s.%N)
    tf="$out/T.tfm"; [ $tool = elastix ] && tf="$out/TransformParameters.0.txt"
    err=$("$cf" coregister-error "$c/truth.tfm" "$tf" --mask "$mask")
    results+=$(python3 -c "import json,sys; e=json.loads(sys.argv[1]); print(json.dumps({'case': sys.argv[2], 'tool': sys.argv[3], 'repeat': int(sys.argv[7]), 'command': sys.argv[8], 'seconds': float(sys.argv[4]) - float(sys.argv[5]), 'mean_mm': e['mean_mm'], 'max_mm': e['max_mm'], 'rss_mb': int(open(sys.argv[6]).read().split()[-1]) / 1024}))" "$err" "$(basename "$c")" "$tool" "$end" "$start" "$out/rss_kb" "$rep" "${cmd[*]}")","
done
done
done
results="${results%,}]"
python3 - "$results" "$work/cases.json" "$(nproc)" "$(cut -d' ' -f1 /proc/loadavg)" "$load_start" "$(elastix --version 2>&1 | tail -n1)" <<'PY'
import json, statistics, sys
rows = json.loads(sys.argv[1])
cases = json.load(open(sys.argv[2]))
summary = {}
for tool in sorted({r['tool'] for r in rows}):
    rs = [r for r in rows if r['tool'] == tool]
    summary[tool] = {
        'runs': len(rs),
        'seconds_median': statistics.median(r['seconds'] for r in rs),
        'seconds_min': min(r['seconds'] for r in rs),
        'seconds_max': max(r['seconds'] for r in rs),
        'mean_mm_median': statistics.median(r['mean_mm'] for r in rs),
        'mean_mm_worst': max(r['mean_mm'] for r in rs),
        'max_mm_worst': max(r['max_mm'] for r in rs),
        'rss_mb_peak': max(r['rss_mb'] for r in rs),
    }
if 'ours_mattes' in summary and 'elastix' in summary:
    summary['elastix_over_ours_seconds'] = summary['elastix']['seconds_median'] / summary['ours_mattes']['seconds_median']
print(json.dumps({'bench': 'coregister_vs_elastix', 'cases': len(cases), 'cpus': int(sys.argv[3]),
                  'loadavg_1min_at_start': float(sys.argv[5]), 'loadavg_1min_at_end': float(sys.argv[4]),
                  'elastix_version': sys.argv[6], 'summary': summary, 'runs': rows, 'truth': cases}, indent=1))
PY
