"""Every held-out run's MRE (defaults), one column per set and test, cases side by side.

Reads heldout_runs.csv beside this file, writes heldout.png. PIL only (no matplotlib here).
"""
import csv
import os
from PIL import Image, ImageDraw

here = os.path.dirname(os.path.abspath(__file__))
rows = list(csv.DictReader(open(os.path.join(here, "heldout_runs.csv"))))
sets = sorted({r["set"] for r in rows})
tests = ["from_landmarks", "proto", "wide5"]
W, H, left, top, bottom = 1180, 520, 60, 40, 90
col_w = (W - left - 20) / len(sets)
y_max = 8.0
img = Image.new("RGB", (W, H), "white")
d = ImageDraw.Draw(img)


def y_of(mre):
    return top + (H - top - bottom) * (1 - min(mre, y_max) / y_max)


for mm in range(0, 9):
    y = y_of(mm)
    d.line([(left, y), (W - 20, y)], fill=(225, 225, 225))
    d.text((left - 30, y - 6), f"{mm}", fill="black")
d.line([(left, y_of(3)), (W - 20, y_of(3))], fill=(200, 0, 0), width=2)
d.text((W - 120, y_of(3) - 16), "MRE 3 mm", fill=(200, 0, 0))
colours = {"case_0000": (31, 119, 180), "case_0001": (255, 127, 14), "case_0002": (44, 160, 44), "case_0003": (148, 103, 189),
           "case_0004": (140, 86, 75), "case_0005": (227, 119, 194), "case_0006": (127, 127, 127), "case_0007": (188, 189, 34)}
for si, s in enumerate(sets):
    x0 = left + si * col_w
    d.line([(x0, top), (x0, H - bottom)], fill=(180, 180, 180))
    for ti, t in enumerate(tests):
        xt = x0 + (ti + 0.5) * col_w / 3
        runs = [r for r in rows if r["set"] == s and r["test"] == t]
        cases = sorted({r["case"] for r in runs})
        for r in runs:
            ci = cases.index(r["case"])
            x = xt + (ci - (len(cases) - 1) / 2) * 3.2
            y = y_of(float(r["mre_defaults_mm"]))
            d.ellipse([x - 2, y - 2, x + 2, y + 2], fill=colours.get(r["case"], (0, 0, 0)))
        ok = sum(float(r["mre_defaults_mm"]) < 3 for r in runs)
        d.text((xt - 14, H - bottom + 22), f"{ok}/{len(runs)}", fill="black")
        d.text((xt - 8, H - bottom + 6), ["lm", "pr", "wd"][ti], fill=(90, 90, 90))
    d.text((x0 + 8, H - bottom + 44), s, fill="black")
d.text((left, 10), "Held-out sets (thirty-seventh session): MRE of every run with the defaults; lm = from the landmarks, "
       "pr = protocol 4 x 10, wd = wide 4 x 5; colour = case", fill="black")
d.text((left, H - 22), "r2x_*: --size 640x427, rs_*: --size 320x213, --dslr-fraction 0, the bundled head. Runs above 8 mm drawn at 8.",
       fill=(90, 90, 90))
img.save(os.path.join(here, "heldout.png"))
