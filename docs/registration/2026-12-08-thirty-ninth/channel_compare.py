import csv, json, sys, os, math, collections
D='/work/main/docs/registration'
out=sys.argv[1]
base={}
for r in csv.DictReader(open(D+'/2026-12-07-thirty-eighth/final_stages_only_runs.csv')):
    base[(r['set'],r['test'],r['case'],int(r['trial']))]=float(r['mre_variant_mm'])
for r in []:
    if r['variant']!='planar_flip': continue
    t={'from_landmarks':'lm','proto':'proto'}.get(r['test'],'wide')
    base[(r['set'],t,r['case'],int(r['trial']))]=float(r['mre_mm'])
for r in []:
    t={'from_landmarks':'lm','proto':'proto'}.get(r['test'],'wide')
    base[(r['set'],t,r['case'],int(r['trial']))]=float(r['mre_defaults_mm'])
H=['r2x_1501','r2x_1511','r2x_1521','r2x_1531','rs_1601','rs_1611','rs_1621','rs_1631']
T=['ev8','evf','ev12','evlamp','evtilt','evmess','evsmall','evsmall2x','chris','seg3d','mni152','dicom']
agg=collections.defaultdict(lambda:[0,0,0,[]]); rows=[]
for grp,sets in (('twelve',T),('held',H)):
  for s in sets:
    for t in ('lm','proto','wide'):
        f=f'{out}/{s}_{t}.json'
        if not os.path.exists(f): continue
        j=json.load(open(f)); d=[]; nb=nv=0
        for r in j['runs']:
            k=(s,t,r['case'],r['trial']); v=r['registered']['mre_mm']
            if k not in base: print('missing',k); continue
            b=base[k]; d.append(v-b); nb+=b<3; nv+=v<3
            rows.append((grp,s,t,r['case'],r['trial'],b,v,r['evaluations']))
            if (b<3)!=(v<3) or abs(v-b)>1.5: print(f'   {s} {t} {r["case"]} {r["trial"]}: {b:.2f} -> {v:.2f}')
        m=sum(d)/len(d); se=(sum((x-m)**2 for x in d)/(len(d)-1))**.5/len(d)**.5 if len(d)>1 else 0
        print(f'{s:10s} {t:5s} n={len(d):3d} pass {nb:3d} -> {nv:3d}  diff {m:+.3f} +- {se:.3f}')
        a=agg[(grp,t)]; a[0]+=len(d); a[1]+=nb; a[2]+=nv; a[3]+=d
for k,a in sorted(agg.items()):
    d=a[3]; m=sum(d)/len(d); se=(sum((x-m)**2 for x in d)/(len(d)-1))**.5/len(d)**.5 if len(d)>1 else 0
    print(f'TOTAL {k[0]:6s} {k[1]:5s} n={a[0]} pass {a[1]} -> {a[2]}  diff {m:+.3f} +- {se:.3f}')
if len(sys.argv)>2:
    w=csv.writer(open(sys.argv[2],'w')); w.writerow(['group','set','test','case','trial','mre_defaults_mm','mre_variant_mm','evaluations_variant']); w.writerows(rows)
