#!/bin/bash
# Rebuilds docs/gallery/ (the overlay part): fused pictures of a phantom case made from the
# bundled MRI, the T1 alone and multimodal (T1 + a CT + an fMRI map, co-registered by the plan).
#   scripts/make-gallery.sh [BUILD_DIR]        (CF=/path/to/cortexfuse overrides the binary)
# Steps:
#  1. one phantom case of the bundled T1 (`cortexfuse phantom --seed 21`) and its registration;
#  2. a CT-like scan of the same head (skull from the T1) with a known misalignment;
#  3. a synthetic fMRI t-map under the exposed cortex (the photo's ROI centre cast back onto the
#     brain surface); 2 and 3 need Debian's python3 with python3-nibabel and python3-scipy;
#  4. `cortexfuse plan --t1 T1 --ct CT --fmri MAP` (co-registers the CT, thresholds the map);
#  5. `cortexfuse overlay` with the registered pose at 50 % photo opacity: once without the
#     plan's modalities (T1 only, CPU ray caster), once with --plan (GL fusion scene).
# docs/gallery/ then holds exactly what this makes (everything else there is removed, README.md
# kept): the pictures as JPEG (quality 88, Debian's python3-pil) to keep the repository small.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$root/build}
cf=${CF:-$build/cli/cortexfuse}
[ -x "$cf" ] || { echo "make-gallery: no $cf (build first)" >&2; exit 1; }
work=$(mktemp -d /tmp/cf_gallery.XXXXXX)
trap 'rm -rf "$work"' EXIT
out=$root/docs/gallery
mkdir -p "$out"
t1=$root/data/t1_head_mne_ecog.nii.gz
mask=$root/data/brainmask_mne_ecog_binary.nii.gz
size=${GALLERY_SIZE:-360x240}   # the photo's size; the fused pictures have the same
width=${size%x*}
py=${PYTHON:-/usr/bin/python3}   # Debian python3 with python3-numpy and python3-nibabel

"$cf" phantom "$work/ph" --n 1 --seed 21 --size "$size" --fixed-size --dslr-fraction 0 --gauze-prob 0 --blood-prob 0 --quiet
case=$work/ph/case_0000
"$cf" register "$case" --out "$work/result.json"

# 1. T1 only (and the ROI centre cast back onto the brain surface for the fMRI map).
"$cf" plan --t1 "$t1" --brain-mask "$mask" --out "$work/plan_t1" --max-triangles 150000
roi_c=$(python3 -c "import json,sys; r=json.load(open(sys.argv[1])); p=r['points'] if isinstance(r,dict) else r; p=[(q['x'],q['y']) if isinstance(q,dict) else q for q in p]; print('%.1f,%.1f' % (sum(x for x,_ in p)/len(p), sum(y for _,y in p)/len(p)))" "$case/roi.json")
"$cf" overlay "$case" "$work/result.json" --out "$work/ov_t1" --plan "$work/plan_t1" --opacity 0.5 \
  --view-width "$width" --yaw -35 --yaw 35 --pitch 30 --cast-back "$roi_c"

# 2. A CT-like scan of the same head: bone where the T1 is dark between the scalp and the
#    brain, soft tissue elsewhere in the head, air outside; misaligned by a known rigid motion
#    (8 deg about S, 5 deg about R, (6, -8, 5) mm) written into its header, so the plan's
#    co-registration has to find it. 3. An fMRI t-map: a Gaussian activation (peak t = 8,
#    sigma 5 mm) centred 4 mm under the exposed cortex at the ROI's centre, noise below threshold.
"$py" - "$t1" "$mask" "$work/ov_t1/overlay.json" "$work/ct.nii.gz" "$work/fmri_tmap.nii.gz" <<'PY'
import json, sys
import nibabel as nib, numpy as np
from scipy import ndimage as ndi
t1 = nib.load(sys.argv[1]); a = np.asarray(t1.dataobj, np.float32)
brain = np.asarray(nib.load(sys.argv[2]).dataobj) > 0
hi = np.percentile(a[a > 0], 99)
head = ndi.binary_fill_holes(ndi.binary_closing(a > 0.12 * hi, iterations=3))
inner = ndi.binary_erosion(head, iterations=3)                # below the scalp
bone = inner & ~ndi.binary_dilation(brain, iterations=2) & (a < 0.25 * hi)
ct = np.where(head, 40.0, -1000.0) + np.where(bone, 1160.0, 0.0)
ct += np.random.default_rng(1).normal(0, 10, ct.shape) * head
def rot(axis, deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg)); i, j = [k for k in range(3) if k != axis]
    r = np.eye(4); r[i, i] = c; r[i, j] = -s; r[j, i] = s; r[j, j] = c; return r
move = rot(2, 8) @ rot(0, 5); move[:3, 3] = [-6.0, 8.0, 5.0]   # RAS: (6, -8, 5) mm in LPS
nib.save(nib.Nifti1Image(ct.astype(np.int16), move @ t1.affine), sys.argv[4])
# The truth as an ITK transform (T1 world -> CT world, LPS): F move F with F = diag(-1, -1, 1).
F = np.diag([-1.0, -1.0, 1.0, 1.0]); M = F @ move @ F
open(sys.argv[4].replace(".nii.gz", "_truth.tfm"), "w").write(
    "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\nParameters: %s\nFixedParameters: 0 0 0\n"
    % " ".join("%.12g" % v for v in list(M[:3, :3].ravel()) + list(M[:3, 3])))
ov = json.load(open(sys.argv[3]))
p = np.array(ov["cast_back"][0]["p_world_mm"])
T = np.array(ov["views"][0]["T_camera_from_world"], float).reshape(4, 4)
c_w = -T[:3, :3].T @ T[:3, 3]
centre = p + 4 * (p - c_w) / np.linalg.norm(p - c_w)
ijk = np.indices(a.shape).reshape(3, -1).T
lps = nib.affines.apply_affine(t1.affine, ijk) * np.array([-1, -1, 1])
t = np.random.default_rng(3).normal(0, 0.8, len(lps)) + 8.0 * np.exp(-np.sum((lps - centre) ** 2, axis=1) / (2 * 5.0 ** 2))
nib.save(nib.Nifti1Image(t.reshape(a.shape).astype(np.float32), t1.affine), sys.argv[5])
PY

# 4. The plan with both, 5. the multimodal overlay.
"$cf" plan --t1 "$t1" --brain-mask "$mask" --ct "$work/ct.nii.gz" --fmri "$work/fmri_tmap.nii.gz" \
  --out "$work/plan" --max-triangles 150000
"$cf" overlay "$case" "$work/result.json" --out "$work/ov_mm" --plan "$work/plan" --opacity 0.5 \
  --view-width "$width" --yaw -35 --yaw 35 --pitch 30

photo=$(ls "$case"/photo.* | head -n1)
find "$out" -mindepth 1 -maxdepth 1 ! -name README.md -exec rm -rf {} +
jpeg() { "$py" -c "import sys; from PIL import Image; Image.open(sys.argv[1]).convert('RGB').save(sys.argv[2], quality=88, optimize=True)" "$1" "$2"; }
jpeg "$photo" "$out/photo.jpg"
jpeg "$work/ov_t1/fused_camera.png" "$out/fused_camera_t1.jpg"
for f in fused_camera fused_yaw-35 fused_yaw35 fused_pitch30; do
  jpeg "$work/ov_mm/$f.png" "$out/${f}_multimodal.jpg"
done
cp "$work/ov_mm/overlay.json" "$out/overlay_multimodal.json"
python3 -c "import json,sys; p=json.load(open(sys.argv[1])); print(json.dumps({s['step']: {k: v for k, v in s.items() if k in ('seconds','nmi','nmi_after','overlap','clusters','voxels_kept','transform')} for s in p.get('steps', []) if 'step' in s}, indent=1))" "$work/plan/plan.json" > "$out/plan_summary.json" || true
# The plan's CT co-registration against the known misalignment, over the brain.
"$cf" coregister-error "$work/ct_truth.tfm" "$work/plan/ct_to_t1.tfm" --mask "$mask" > "$out/ct_coregistration_error.json"
echo "make-gallery: wrote $(ls "$out" | wc -l) entries to $out"
