# usage: sweep39.sh BIN PARAMS OUTDIR [phases...]  phases: hproto tlm hlm tproto hwide twide
B=$1; P=$2; O=$3; shift 3; mkdir -p $O
H="r2x_1501 r2x_1511 r2x_1521 r2x_1531 rs_1601 rs_1611 rs_1621 rs_1631"
T="ev8 evf ev12 evlamp evtilt evmess evsmall evsmall2x chris seg3d mni152 dicom"
ev(){ s=$1; t=$2; shift 2; [ -f $O/${s}_$t.json ] || $B evaluate sets/$s --params $P --json $O/${s}_$t.json "$@" > $O/${s}_$t.log 2>&1; echo "$(date +%T) $s $t"; }
for ph in "$@"; do case $ph in
hproto) for s in $H; do ev $s proto --limit-cases 4 --trials 10; done;;
hlm) for s in $H; do ev $s lm --trials 0; done;;
tlm) for s in $T; do ev $s lm --trials 0 --limit-cases 8; done;;
tproto) for s in $T; do ev $s proto --limit-cases 4 --trials 10; done;;
hwide) for s in $H; do ev $s wide --limit-cases 4 --trials 5 --wide; done;;
twide) for s in $T; do case $s in ev12) n=3;; chris|seg3d|mni152|dicom) n=2;; *) n=5;; esac; ev $s wide --trials $n --wide; done;;
esac; done
echo ALLDONE
