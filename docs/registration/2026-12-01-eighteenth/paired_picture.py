#!/usr/bin/python3
# The picture of docs/registration.md's "The landmarks' other fits for a given pose": every
# paired run (the seventeenth session's defaults against landmark_moves), and chris case 0003
# trial by trial. Reads the two runs.csv files beside each other in docs/registration/.
import csv, collections, os
import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt

here = os.path.dirname(os.path.abspath(__file__))
base = {}
for r in csv.DictReader(open(os.path.join(here, "../2026-11-29-seventeenth/runs.csv"))):
    if r["variant"] == "outer_ray_stride_2":
        base[(r["set"], r["test"], r["case"], r["trial"])] = float(r["mre_mm"])
new = {}
for r in csv.DictReader(open(os.path.join(here, "runs.csv"))):
    if r["variant"] == "landmark_moves":
        new[(r["set"], r["test"], r["case"], r["trial"])] = float(r["mre_mm"])
for r in csv.DictReader(open(os.path.join(here, "runs.csv"))):  # sets not re-run: identical
    k = (r["set"], r["test"], r["case"], r["trial"])
    if r["variant"] == "landmark_moves_ungated" and r["set"] != "mni152" and k not in new:
        new[k] = float(r["mre_mm"])

fig, ax = plt.subplots(1, 2, figsize=(12, 5.4))
colours = {"ev8": "#1f77b4", "evf": "#17becf", "ev12": "#9467bd", "chris": "#d62728", "seg3d": "#2ca02c",
           "mni152": "#7f7f7f", "dicom": "#ff7f0e"}
by_set = collections.defaultdict(list)
for k, b in base.items():
    if k in new:
        by_set[k[0]].append((b, new[k]))
for s, pts in sorted(by_set.items()):
    ax[0].scatter([p[0] for p in pts], [p[1] for p in pts], s=10, alpha=0.7, c=colours[s], label=f"{s} ({len(pts)})")
ax[0].plot([0.05, 60], [0.05, 60], "k-", lw=0.6)
ax[0].axvline(3, color="r", lw=0.6, ls="--")
ax[0].axhline(3, color="r", lw=0.6, ls="--")
ax[0].set_xscale("log"); ax[0].set_yscale("log")
ax[0].set_xlabel("MRE mm, seventeenth session's defaults"); ax[0].set_ylabel("MRE mm, with the landmarks' other fits")
n = sum(len(v) for v in by_set.values())
pb = sum(b < 3 for v in by_set.values() for b, _ in v); pn = sum(m < 3 for v in by_set.values() for _, m in v)
ax[0].set_title(f"every paired run ({n}): {pb} -> {pn} under 3 mm (dashed)")
ax[0].legend(fontsize=8, loc="upper left")

trials = sorted({int(k[3]) for k in base if k[:3] == ("chris", "proto", "case_0003")})
b3 = [base[("chris", "proto", "case_0003", str(t))] for t in trials]
n3 = [new[("chris", "proto", "case_0003", str(t))] for t in trials]
ax[1].plot(trials, b3, "o-", c="#555555", label=f"before: mean {sum(b3)/len(b3):.2f} mm")
ax[1].plot(trials, n3, "o-", c="#d62728", label=f"with the other fits: mean {sum(n3)/len(n3):.2f} mm")
ax[1].axhline(0.67, color="#d62728", lw=0.8, ls=":", label="from the landmarks alone (their fits as starts): 0.67 mm")
ax[1].axhline(3.40, color="k", lw=0.8, ls="--", label="the landmark pose itself: 3.40 mm")
ax[1].set_ylim(0, 5.2); ax[1].set_xticks(trials)
ax[1].set_xlabel("trial (misaligned start, +-10 mm / +-5 deg)"); ax[1].set_ylabel("MRE mm")
ax[1].set_title("chris case 0003 (DSLR, 21 deg view, 4 landmarks), seed protocol")
ax[1].legend(fontsize=8, loc="upper left")
fig.tight_layout()
fig.savefig(os.path.join(here, "landmark_moves.png"), dpi=90)
