# usage: bash sweep.sh CORTEXFUSE PARAMS.json OUTDIR (run in the folder holding sets/, made as in the closing note)
B=$1; P=$2; O=$3; mkdir -p $O
H="r2x_1501 r2x_1511 r2x_1521 r2x_1531 rs_1601 rs_1611 rs_1621 rs_1631"
T="ev8 evf ev12 evlamp evtilt evmess evsmall evsmall2x chris seg3d mni152 dicom"
ev(){ s=$1; t=$2; shift 2; [ -f $O/${s}_$t.json ] || $B evaluate sets/$s --params $P --json $O/${s}_$t.json "$@" > $O/${s}_$t.log 2>&1; echo "$(date +%T) $s $t"; }
for s in $H; do ev $s proto --limit-cases 4 --trials 10; done
for s in $T; do ev $s lm --trials 0 --limit-cases 8; done
for s in $H; do ev $s lm --trials 0 --limit-cases 8; done
for s in $T; do ev $s proto --limit-cases 4 --trials 10; done
for s in $H; do ev $s wide --limit-cases 4 --trials 5 --wide; done
for s in $T; do case $s in ev12) n=3; l=12;; chris|seg3d|mni152|dicom) n=2; l=8;; *) n=5; l=8;; esac; ev $s wide --trials $n --wide --limit-cases $l; done
echo ALLDONE
