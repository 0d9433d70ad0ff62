"""Paired differences of every run, a variant minus the defaults: one column per set and test.

draw(runs_csv, variant_column, out_png, title): the CSV has group, set, test, mre_defaults_mm and
the variant's MRE in variant_column. PIL only. Used by the dated folders' *_picture.py.
"""
import csv
import statistics
from PIL import Image, ImageDraw


def draw(runs_csv, variant_column, out_png, title):
    rows = list(csv.DictReader(open(runs_csv)))
    cols = []
    for r in rows:
        key = (r["group"], r["set"], r["test"])
        if key not in cols:
            cols.append(key)
    W, H, left, top, bottom = max(900, 40 + 22 * len(cols) + 80), 560, 60, 50, 130
    span = 3.0  # mm either side
    img = Image.new("RGB", (W, H), "white")
    d = ImageDraw.Draw(img)


    def y_of(v):
        v = max(-span, min(span, v))
        return top + (H - top - bottom) * (span - v) / (2 * span)


    for mm in (-3, -2, -1, 0, 1, 2, 3):
        d.line([(left, y_of(mm)), (W - 20, y_of(mm))], fill=(200, 200, 200) if mm else (0, 0, 0))
        d.text((left - 30, y_of(mm) - 6), f"{mm:+d}", fill="black")
    step = (W - left - 20) / len(cols)
    for i, (group, s, test) in enumerate(cols):
        x = left + (i + 0.5) * step
        diffs = [float(r[variant_column]) - float(r["mre_defaults_mm"]) for r in rows
                 if (r["group"], r["set"], r["test"]) == (group, s, test)]
        for k, v in enumerate(diffs):
            colour = (0, 130, 0) if v < -0.1 else (200, 0, 0) if v > 0.1 else (120, 120, 120)
            xx = x + ((k % 5) - 2) * 2
            d.ellipse([xx - 1.5, y_of(v) - 1.5, xx + 1.5, y_of(v) + 1.5], fill=colour)
        m = statistics.mean(diffs)
        d.line([(x - 7, y_of(m)), (x + 7, y_of(m))], fill=(0, 0, 200), width=3)
        label = f"{s} {test}"
        for j, ch in enumerate(label[:18]):
            d.text((x - 3, H - bottom + 6 + j * 7), ch, fill=(0, 0, 0) if group == "twelve" else (150, 60, 0))
    d.text((left, 10), title + ", MRE per run (mm; negative: nearer the truth); blue bar: the set's mean", fill="black")
    d.text((left, 26), "black labels: the twelve sets; brown: the eight held-out sets; green/red: over 0.1 mm nearer/further; "
           "clipped at +-3 mm", fill=(90, 90, 90))
    img.save(out_png)
