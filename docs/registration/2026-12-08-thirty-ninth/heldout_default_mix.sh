# The seven fresh held-out sets of the thirty-ninth session (run from the evaluation folder, with
# S=../shared/data and masks/M_<head>.nii.gz from `cortexfuse skullstrip`), then the defaults on
# each: from the landmarks, the protocol, the wide test.
B=${B:-cortexfuse}; S=${S:-/work/shared/data}; O=out/newheld; mkdir -p $O
$B phantom sets/hb_1701 --quiet --n 8 --seed 1701
$B phantom sets/hb_1751 --quiet --n 8 --seed 1751
$B phantom sets/hb_1761 --quiet --n 8 --seed 1761
$B phantom sets/hc_1711 --quiet --n 8 --seed 1711 --volume $S/t1_head_chris.nii.gz --mask masks/M_chris.nii.gz
$B phantom sets/hs_1721 --quiet --n 8 --seed 1721 --volume $S/t1_head_seg3d.nii.gz --mask masks/M_seg3d.nii.gz
$B phantom sets/hd_1731 --quiet --n 8 --seed 1731 --volume $S/dicom/mr_head_t1_sag_siemens --mask masks/M_dicom.nii.gz
$B phantom sets/hm_1741 --quiet --n 8 --seed 1741 --volume $S/mni152_fsl_t1_2mm_head.nii.gz --mask masks/M_mni152.nii.gz
ev(){ s=$1; t=$2; shift 2; [ -f $O/${s}_$t.json ] || $B evaluate sets/$s --json $O/${s}_$t.json "$@" > $O/${s}_$t.log 2>&1; echo "$(date +%T) $s $t"; }
for s in hb_1701 hb_1751 hb_1761 hc_1711 hs_1721 hd_1731 hm_1741; do ev $s lm --trials 0; ev $s proto --limit-cases 4 --trials 10; done
for s in hb_1701 hc_1711 hs_1721 hd_1731 hm_1741; do ev $s wide --limit-cases 4 --trials 5 --wide; done
