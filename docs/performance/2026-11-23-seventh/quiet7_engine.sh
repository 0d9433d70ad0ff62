#!/bin/bash
# Quiet-window benchmarks of the seventh session. Usage: quiet7.sh BUILD (a full release build at main HEAD)
set -u
B=$1; O=/tmp/q7; R=${R:-$(cd $(dirname $B) && pwd)}
NEW=$B/cli/cortexfuse; BASE=/tmp/cf_base7
log() { echo "[$(date -u +%H:%M:%S) load $(cut -d' ' -f1 /proc/loadavg)] $*" | tee -a $O/log.txt; }
cd $R
log "start"
# 1. CPU vs VTK, both sizes, 3 rounds (script alternates)
log "render_vs_vtk"
BUILD_DIR=$B SIZES="375x250 1280x800" FRAMES=30 WARMUP=5 ROUNDS=3 THREADS=2 bench/render_vs_vtk.sh > $O/render_vs_vtk.json 2> $O/render_vs_vtk.err
log "render_vs_vtk done"
# 2. CPU new vs base (58f25a6), interleaved, 3 rounds, 60 frames, and surface-only brain
for r in 1 2 3; do
  for b in BASE NEW; do eval exe=\$$b
    $exe bench render --threads 2 --frames 60 --json > $O/cpu_skin_${b}_$r.json 2>/dev/null
    $exe bench render --threads 2 --frames 100 --surface-only --sample-mm 2 --tf cortex_t1 --mask data/brainmask_mne_ecog_binary.nii.gz --json > $O/cpu_surf_${b}_$r.json 2>/dev/null
    LP_NUM_THREADS=2 $exe bench render --renderer gl --frames 30 --json > $O/gl_skin_${b}_$r.json 2>/dev/null
  done
  log "round $r"
done
LP_NUM_THREADS=2 $NEW bench render --renderer gl --size 1280x800 --frames 5 --warmup 2 --json > $O/gl_skin_NEW_1280.json 2>/dev/null
log "gl 1280 done"
# 3. registration, 3 runs new, 1 base
for r in 1 2 3; do $NEW bench register --cases 4 --threads 2 --json > $O/register_NEW_$r.json 2>/dev/null; log "register $r"; done
$BASE bench register --cases 4 --threads 2 --json > $O/register_BASE_1.json 2>/dev/null
log "register base done"
