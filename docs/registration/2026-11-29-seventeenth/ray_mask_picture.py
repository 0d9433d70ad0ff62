#!/usr/bin/python3
"""The picture docs/registration.md shows for outer_ray_stride (seventeenth session).

Input: the images a temporary dump in Scorer::similarity wrote (ray_mask_dump.patch, beside
this file) for `cortexfuse landscape CASE --width-px 250 --fwhm-mm 2 --range-mm 0 --range-deg 0
--steps 3 --params {"outer_ray_stride": S}` with S = 1 and 2, CF_DUMP_DIR=DIR.
Usage: ray_mask_picture.py DIR OUT.jpg
"""
import sys
import cv2
import numpy as np

d, out = sys.argv[1], sys.argv[2]
mask = cv2.imread(f"{d}/s2_mask.png", 0)
valid = cv2.imread(f"{d}/s2_valid.png", 0)
g1 = cv2.imread(f"{d}/s1_grey.png", 0)
g2 = cv2.imread(f"{d}/s2_grey.png", 0)
def blur(s):
    fs = cv2.FileStorage(f"{d}/s{s}_blur.yml", cv2.FILE_STORAGE_READ)
    return fs.getNode("b").mat()
b1, b2 = blur(1), blur(2)
h, w = mask.shape
# 1: which rays are cast: white = every pixel (within the blur's reach of a usable ROI pixel),
# grey dots = the lattice beyond, black = interpolated; usable ROI pixels tinted green.
m = np.zeros((h, w, 3), np.uint8)
m[mask > 0] = (150, 150, 150)
# Inside the blur's reach every pixel is cast, so a cast pixel with a cast neighbour is there.
near = cv2.dilate(cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))), np.ones((3, 3), np.uint8))
m[(mask > 0) & (near > 0)] = (255, 255, 255)
m[valid > 0] = (90, 200, 90)
# 2, 3: the rendering with every ray and with stride 2 (the left-out pixels interpolated).
c1 = cv2.cvtColor(g1, cv2.COLOR_GRAY2BGR)
c2 = cv2.cvtColor(g2, cv2.COLOR_GRAY2BGR)
# 4: what the similarity sees, the filtered rendering: its difference at usable pixels, x200.
diff = np.abs(b2 - b1)
dv = np.zeros((h, w), np.uint8)
dv[valid > 0] = np.clip(diff[valid > 0] * 200 * 255, 0, 255).astype(np.uint8)
c4 = cv2.applyColorMap(dv, cv2.COLORMAP_INFERNO)
c4[valid == 0] = (40, 40, 40)
S = 3
tiles = [cv2.resize(t, (w * S, h * S), interpolation=cv2.INTER_NEAREST) for t in (m, c1, c2, c4)]
labels = ["rays cast (stride 2)", "every ray", "stride 2, filled", "|filtered diff| x200 at ROI"]
for t, l in zip(tiles, labels):
    cv2.putText(t, l, (6, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(t, l, (6, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
pic = np.hstack([np.hstack([t, np.full((h * S, 6, 3), 255, np.uint8)]) for t in tiles])
cv2.imwrite(out, pic, [cv2.IMWRITE_JPEG_QUALITY, 88])
print(f"cast {int((mask > 0).sum())} of {h * w} rays; filtered difference at usable pixels: "
      f"max {diff[valid > 0].max():.4f}, mean {diff[valid > 0].mean():.5f} (filtered range 0..1)")
