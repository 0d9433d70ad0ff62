#!/usr/bin/python3
# The picture of docs/registration.md's "The landmarks' other fits past the screen, and each
# finalist's own light": every protocol and wide run paired with the eighteenth session's
# defaults (left), and per set the mean paired difference of the two variants (right).
# Reads this folder's runs.csv and the eighteenth session's beside it.
import csv, collections, os, statistics
import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt

here = os.path.dirname(os.path.abspath(__file__))
base = {}
for r in csv.DictReader(open(os.path.join(here, "../2026-12-01-eighteenth/runs.csv"))):
    k = (r["set"], r["test"], r["case"], r["trial"])
    # the gated default where it was run (chris, MNI152), else the ungated runs (the same runs there)
    if r["variant"] == "landmark_moves" or (r["variant"] == "landmark_moves_ungated" and k not in base):
        base[k] = float(r["mre_mm"])
new = collections.defaultdict(dict)
for r in csv.DictReader(open(os.path.join(here, "runs.csv"))):
    if r["test"] != "from_landmarks":
        new[r["variant"]][(r["set"], r["test"], r["case"], r["trial"])] = float(r["mre_mm"])

colours = {"ev8": "#1f77b4", "evf": "#17becf", "ev12": "#9467bd", "chris": "#d62728", "seg3d": "#2ca02c",
           "mni152": "#7f7f7f", "dicom": "#ff7f0e"}
final = new["search_keep_fits_light_per_finalist"]
fig, ax = plt.subplots(1, 2, figsize=(13, 5.4))
by_set = collections.defaultdict(list)
for k, m in final.items():
    by_set[k[0]].append((base[k], m))
for s, pts in sorted(by_set.items()):
    ax[0].scatter([p[0] for p in pts], [p[1] for p in pts], s=10, alpha=0.7, c=colours[s], label=f"{s} ({len(pts)})")
ax[0].plot([0.05, 60], [0.05, 60], "k-", lw=0.6)
ax[0].axvline(3, color="r", lw=0.6, ls="--"); ax[0].axhline(3, color="r", lw=0.6, ls="--")
ax[0].set_xscale("log"); ax[0].set_yscale("log")
ax[0].set_xlabel("MRE mm, eighteenth session's defaults")
ax[0].set_ylabel("MRE mm, fits past the screen + each finalist's light")
n = sum(len(v) for v in by_set.values())
pb = sum(b < 3 for v in by_set.values() for b, _ in v); pn = sum(m < 3 for v in by_set.values() for _, m in v)
ax[0].set_title(f"every paired run ({n}): {pb} -> {pn} under 3 mm (dashed)")
ax[0].legend(fontsize=8, loc="upper left")

sets = ["ev8", "evf", "ev12", "chris", "seg3d", "mni152", "dicom"]
for j, (variant, label, c) in enumerate([("search_keep_fits", "fits past the screen", "#888888"),
                                         ("search_keep_fits_light_per_finalist", "+ each finalist's light", "#d62728")]):
    for t, (tests, marker) in enumerate([(("proto",), "o"), (("wide", "wide4x10", "wide5", "wide3"), "s")]):
        xs, ys, es = [], [], []
        for i, s in enumerate(sets):
            d = [m - base[k] for k, m in new[variant].items() if k[0] == s and k[1] in tests]
            if len(d) < 2: continue
            xs.append(i + (j - 0.5) * 0.3 + t * 0.08); ys.append(statistics.mean(d))
            es.append(statistics.stdev(d) / len(d) ** 0.5)
        ax[1].errorbar(xs, ys, yerr=es, fmt=marker, c=c, ms=5, capsize=2,
                       label=f"{label}, {'protocol' if t == 0 else 'wide'}")
ax[1].axhline(0, color="k", lw=0.6)
ax[1].set_xticks(range(len(sets))); ax[1].set_xticklabels(sets)
ax[1].set_ylabel("paired MRE difference mm (mean +- se), below 0: better")
ax[1].set_title("per set, against the eighteenth session's defaults")
ax[1].legend(fontsize=8)
fig.tight_layout()
fig.savefig(os.path.join(here, "paired.png"), dpi=90)
