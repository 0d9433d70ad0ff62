# The widened fit's lead per run, by set (widened_fit_lead.png).
# Usage: python3 lead_picture.py RUNS.csv BASE_RUNS.csv OUT.png, where RUNS.csv holds the option's runs
# (this folder's runs.csv, variant by_image_F) and BASE_RUNS.csv the defaults' (the thirty-fourth
# session's runs.csv, variant planar_flip); the wide test's names (wide, wide3, wide5) are matched as one.
import csv, sys
from PIL import Image, ImageDraw
key = lambda r: (r['set'], 'wide' if r['test'].startswith('wide') else r['test'], r['case'], r['trial'])
base = {key(r): r for r in csv.DictReader(open(sys.argv[2])) if r['variant'] == 'planar_flip'}
rows = [r for r in csv.DictReader(open(sys.argv[1])) if r['lead'] and r['variant'] in ('by_image_F', 'img15F')]
sets = []
for r in rows:
    if r['set'] not in sets: sets.append(r['set'])
W, H, left, top, rowh = 900, 80 + 40 * len(sets), 110, 60, 40
lo, hi = -0.06, 0.06
img = Image.new('RGB', (W, H), 'white'); d = ImageDraw.Draw(img)
X = lambda v: left + int((W - left - 20) * (min(max(v, lo), hi) - lo) / (hi - lo))
for t in range(-6, 7):
    v = t / 100; d.line([(X(v), top - 5), (X(v), H - 30)], fill=(225, 225, 225)); d.text((X(v) - 12, H - 25), f'{v:+.2f}', fill=(60, 60, 60))
d.line([(X(0.02), top - 10), (X(0.02), H - 30)], fill=(200, 0, 0), width=2)
d.text((left, 8), "The widened fit's lead over the other candidates (red line: the margin, 0.02; clamped to +-0.06)", fill=(0, 0, 0))
d.text((left, 24), "dot red: the defaults' run of the same case and start failed (MRE >= 3 mm); ring: the prior ended widened (red ring: and this run failed)", fill=(0, 0, 0))
import random; random.seed(1)
for i, s in enumerate(sets):
    y = top + 40 * i + 20
    d.text((8, y - 6), s, fill=(0, 0, 0))
    for r in rows:
        if r['set'] != s: continue
        k = key(r)
        failed = float(base[k]['mre_mm']) >= 3 if k in base else False
        x = X(float(r['lead'])); yy = y + random.randint(-12, 12)
        c = (210, 40, 40) if failed else (60, 150, 60)
        d.ellipse([x - 3, yy - 3, x + 3, yy + 3], fill=c)
        if r['landmark_prior_widened'] == 'True':
            d.ellipse([x - 6, yy - 6, x + 6, yy + 6], outline=(220, 0, 0) if float(r['mre_mm']) >= 3 else (0, 0, 0), width=2 if float(r['mre_mm']) >= 3 else 1)
img.save(sys.argv[3])
print('wrote', sys.argv[3], len(rows), 'runs with a widened fit')
