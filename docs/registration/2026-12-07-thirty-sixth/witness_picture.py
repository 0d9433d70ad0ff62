# Each run whose widened fit led by the margin (0.02): where the photo's peak lay from the best
# plain candidate (x) and how clearly the widened fit's peak stood (y), coloured by what widening
# did to it against the defaults (the thirty-sixth session; witness_runs.csv from this folder). Usage: python3 witness_picture.py witness_runs.csv OUT.png APART_MM PROMINENCE
import csv, sys
from PIL import Image, ImageDraw
rows = [r for r in csv.DictReader(open(sys.argv[1])) if r['lead'] and float(r['lead']) >= 0.02]
a, q = float(sys.argv[3]), float(sys.argv[4])
W, H, left, top, bottom, right = 900, 620, 70, 50, 60, 230
X = lambda v: left + (W - left - right) * min(max(v, 0), 10) / 10
Y = lambda v: H - bottom - (H - top - bottom) * min(max(v, 0), 1)
img = Image.new('RGB', (W, H), 'white'); d = ImageDraw.Draw(img)
for t in range(0, 11):
    d.line([(X(t), top), (X(t), H - bottom)], fill=(230, 230, 230)); d.text((X(t) - 4, H - bottom + 6), str(t), fill=(60, 60, 60))
for t in range(0, 11):
    v = t / 10; d.line([(left, Y(v)), (W - right, Y(v))], fill=(230, 230, 230)); d.text((left - 30, Y(v) - 6), f'{v:.1f}', fill=(60, 60, 60))
d.text((left, H - 28), "the photo's peak from the best plain candidate (mm, tx and ty averaged)", fill=(0, 0, 0))
d.text((8, 8), "Runs where the widened fit led by 0.02: what widening did (dashed: the witnesses' thresholds; widened only top right)", fill=(0, 0, 0))
d.text((8, 24), "y: the widened fit's peak prominence (tx and ty averaged)", fill=(0, 0, 0))
for x in range(int(X(a)), W - right, 6): pass
for yy in range(top, H - bottom, 8): d.line([(X(a), yy), (X(a), yy + 4)], fill=(120, 0, 0), width=2)
for xx in range(left, W - right, 8): d.line([(xx, Y(q)), (xx + 4, Y(q))], fill=(120, 0, 0), width=2)
col = lambda dm: (0, 150, 0) if dm <= -0.1 else ((210, 0, 0) if dm >= 0.1 else (140, 140, 140))
shape = {}
for r in rows:
    dm = float(r['mre_widened_mm']) - float(r['mre_defaults_mm'])
    x, y = X(float(r['plain_peak_apart_mm'])), Y(float(r['widened_prominence']))
    c = col(dm); rad = 4 + min(6, abs(dm) * 2)
    if r['held_out'] == '1': d.rectangle([x - rad, y - rad, x + rad, y + rad], outline=c, width=2)
    else: d.ellipse([x - rad, y - rad, x + rad, y + rad], outline=c, width=2)
lx = W - right + 15
for i, (t, c) in enumerate([('nearer the truth by >= 0.1 mm', (0, 150, 0)), ('further by >= 0.1 mm', (210, 0, 0)), ('within 0.1 mm', (140, 140, 140))]):
    d.ellipse([lx, top + 20 * i, lx + 10, top + 20 * i + 10], outline=c, width=2); d.text((lx + 16, top + 20 * i), t, fill=(0, 0, 0))
d.text((lx, top + 70), 'circle: the twelve sets', fill=(0, 0, 0)); d.text((lx, top + 86), 'square: held-out sets', fill=(0, 0, 0))
d.text((lx, top + 102), 'size: how far (mm)', fill=(0, 0, 0))
labels = {}
for r in rows:
    k = (r['set'], r['case'])
    labels.setdefault(k, []).append((float(r['plain_peak_apart_mm']), float(r['widened_prominence'])))
for (s, c), pts in labels.items():
    x = sum(p[0] for p in pts) / len(pts); y = sum(p[1] for p in pts) / len(pts)
    if x >= a or y < q:  # the quadrants the witnesses decide; the crowd top left is in the text
        d.text((X(x) + 8, Y(y) - 14), f'{s} {c[-4:]}', fill=(40, 40, 160))
img.save(sys.argv[2])
