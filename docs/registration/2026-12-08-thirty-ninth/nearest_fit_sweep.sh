B=bin/cf39n; P=nearest.json; O=out/near; mkdir -p $O
ev(){ s=$1; t=$2; shift 2; [ -f $O/${s}_$t.json ] || $B evaluate sets/$s --params $P --json $O/${s}_$t.json "$@" > $O/${s}_$t.log 2>&1; echo "$(date +%T) $s $t"; }
for s in hb_1701 hb_1751 hb_1761 hc_1711 hs_1721 hd_1731 hm_1741 r2x_1501 r2x_1511 r2x_1521 r2x_1531 rs_1601 rs_1611 rs_1621 rs_1631 ev8 evf ev12 evlamp evtilt evmess evsmall evsmall2x chris seg3d mni152 dicom; do ev $s proto --limit-cases 4 --trials 10; done
for s in hb_1701 hc_1711 hs_1721 hd_1731 hm_1741 r2x_1501 r2x_1511 r2x_1521 r2x_1531 rs_1601 rs_1611 rs_1621 rs_1631; do ev $s wide --limit-cases 4 --trials 5 --wide; done
for s in ev8 evf ev12 evlamp evtilt evmess evsmall evsmall2x chris seg3d mni152 dicom; do case $s in ev12) n=3;; chris|seg3d|mni152|dicom) n=2;; *) n=5;; esac; ev $s wide --trials $n --wide; done
echo ALLDONE
