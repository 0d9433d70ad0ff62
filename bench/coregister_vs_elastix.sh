#!/bin/bash
# Rigid co-registration, ours (ITK v4, Mattes and --metric nmi) beside elastix, on the same
# synthetic cases with known truth (a real T1 moved by a random rigid transform, intensities
# remapped non-monotonically): CT-like (0.9 x 0.9 x 2 mm, HU-like values) and mean-EPI-like
# (3 mm voxels, blurred 4 mm FWHM, T2*-like contrast), N_CASES of each kind.
# Prints one JSON object: per kind and tool the median seconds, mean/max error over the brain
# (mm), peak RSS (MB), and runs that ended in an error (a quality gate refusing the result).
#   bench/coregister_vs_elastix.sh [T1] [BRAIN_MASK] [N_CASES] [BUILD_DIR]
# REPEATS=k (environment, default 1) runs every case k times per tool, alternating the tools
# (ours, elastix, ours, ...) so that the machine's load falls on all alike; errors are measured on
# every run. KINDS (default "ct epi") and TOOLS (default "ours_mattes ours_nmi elastix") select.
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
kinds=${KINDS:-ct epi}
tools=${TOOLS:-ours_mattes ours_nmi elastix}
echo "[]" > "$work/cases.json"
for kind in $kinds; do
  "$cf" coregister-synth "$t1" --out "$work/$kind" --n "$n" --seed 7 --kind "$kind" > "$work/cases_$kind.json"
  python3 -c "import json,sys; a=json.load(open(sys.argv[1])); a+=json.load(open(sys.argv[2])); json.dump(a, open(sys.argv[1],'w'))" "$work/cases.json" "$work/cases_$kind.json"
done
threads=$(nproc)
repeats=${REPEATS:-1}
load_start=$(cut -d' ' -f1 /proc/loadavg)
results="["
for kind in $kinds; do
for c in "$work/$kind"/case_*; do
for rep in $(seq 1 "$repeats"); do
  # Each tool timed with its peak RSS. A run of ours that a quality gate refuses (exit 1, one
  # line naming the problem) is recorded as refused, not as a transform.
  for tool in $tools; do
    out="$c/$tool.$rep"; mkdir -p "$out"
    case $tool in
      ours_mattes) cmd=("$cf" coregister "$t1" "$c/moving.nii.gz" --out "$out/T.tfm" --metric mattes --json);;
      ours_nmi)    cmd=("$cf" coregister "$t1" "$c/moving.nii.gz" --out "$out/T.tfm" --metric nmi --json);;
      elastix)     cmd=(elastix -f "$t1" -m "$c/moving.nii.gz" -p "$here/elastix_rigid_mi.txt" -out "$out" -threads "$threads");;
    esac
    start=$(date +%s.%N)
    refused=""
    if ! /usr/bin/time -f "%M" -o "$out/rss_kb" "${cmd[@]}" > "$out/log" 2>&1; then
      if [ "$tool" = elastix ] || ! grep -q "error: moving volume" "$out/log"; then
        echo "$tool failed on $c, see $out/log" >&2; cat "$out/log" >&2; exit 1
      fi
      refused=$(grep "error:" "$out/log" | tail -n1)
    fi
    end=$(date +%s.%N)
    tf="$out/T.tfm"; [ $tool = elastix ] && tf="$out/TransformParameters.0.txt"
    if [ -n "$refused" ]; then err='{"mean_mm": null, "max_mm": null}'; else err=$("$cf" coregister-error "$c/truth.tfm" "$tf" --mask "$mask"); fi
    results+=$(python3 -c "import json,sys; e=json.loads(sys.argv[1]); print(json.dumps({'kind': sys.argv[9], 'case': sys.argv[2], 'tool': sys.argv[3], 'repeat': int(sys.argv[7]), 'command': sys.argv[8], 'seconds': float(sys.argv[4]) - float(sys.argv[5]), 'mean_mm': e['mean_mm'], 'max_mm': e['max_mm'], 'refused': sys.argv[10] or None, 'rss_mb': int(open(sys.argv[6]).read().split()[-1]) / 1024}))" "$err" "$(basename "$c")" "$tool" "$end" "$start" "$out/rss_kb" "$rep" "${cmd[*]}" "$kind" "$refused")","
done
done
done
done
results="${results%,}]"
python3 - "$results" "$work/cases.json" "$(nproc)" "$(cut -d' ' -f1 /proc/loadavg)" "$load_start" "$(elastix --version 2>&1 | tail -n1)" <<'PY'
import json, statistics, sys
rows = json.loads(sys.argv[1])
cases = json.load(open(sys.argv[2]))
summary = {}
for kind in sorted({r['kind'] for r in rows}):
    sk = summary[kind] = {}
    for tool in sorted({r['tool'] for r in rows if r['kind'] == kind}):
        rs = [r for r in rows if r['tool'] == tool and r['kind'] == kind]
        ok = [r for r in rs if r['mean_mm'] is not None]
        sk[tool] = {
            'runs': len(rs),
            'refused': len(rs) - len(ok),
            'seconds_median': statistics.median(r['seconds'] for r in rs),
            'seconds_min': min(r['seconds'] for r in rs),
            'seconds_max': max(r['seconds'] for r in rs),
            'mean_mm_median': statistics.median(r['mean_mm'] for r in ok) if ok else None,
            'mean_mm_worst': max(r['mean_mm'] for r in ok) if ok else None,
            'max_mm_worst': max(r['max_mm'] for r in ok) if ok else None,
            'rss_mb_peak': max(r['rss_mb'] for r in rs),
        }
    for ours in ('ours_mattes', 'ours_nmi'):
        if ours in sk and 'elastix' in sk and not sk[ours]['refused']:
            sk['elastix_over_' + ours + '_seconds'] = sk['elastix']['seconds_median'] / sk[ours]['seconds_median']
print(json.dumps({'bench': 'coregister_vs_elastix', 'cases': len(cases), 'cpus': int(sys.argv[3]),
                  'loadavg_1min_at_start': float(sys.argv[5]), 'loadavg_1min_at_end': float(sys.argv[4]),
                  'elastix_version': sys.argv[6], 'summary': summary, 'runs': rows, 'truth': cases}, indent=1))
PY
