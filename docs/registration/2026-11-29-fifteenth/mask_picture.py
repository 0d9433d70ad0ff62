# Draws blood_mask.jpg: the similarity mask of core/src/registration.cpp's photo_channel(), re-done
# in numpy for the picture (the ROI as a polygon rather than the engine's spline), before (the plain
# median and MAD of the saturation) and after (tissue_median_mad(): the densest quarter starting in
# the lower half, window 15: vessel_mask_window). Blue: glare, gauze, drapes; yellow: vessels and blood.
# Usage: python3 mask_picture.py OUT.jpg CASE_DIR...   (Debian: apt-get install python3-opencv)
import cv2, numpy as np, json, sys, glob
def shorth(a, frac=0.25):
    a = np.sort(a); n = a.size; k = max(1, int(frac * n))
    w = (a[k:] - a[:n - k])[:n // 2 + 1]; i = np.argmin(w); return 0.5 * (a[i] + a[i + k]), w[i]
def tissue(a, win=15):
    m, L = shorth(a); sel = a[np.abs(a - m) <= win * max(1.059 * L, 1e-3)]
    med = np.median(sel); return med, max(np.median(np.abs(sel - med)), 1e-3)
def plain(a):
    med = np.median(a); return med, max(np.median(np.abs(a - med)), 1e-3)
def mask(case, W, robust):
    img = cv2.imread(glob.glob(case + '/photo.*')[0]); h, w = img.shape[:2]; s = W / w
    small = cv2.resize(img, (W, int(round(h * s))), interpolation=cv2.INTER_AREA)
    pts = (np.array(json.load(open(case + '/roi.json'))['points']) * s).astype(np.int32)
    R = np.zeros(small.shape[:2], np.uint8); cv2.fillPoly(R, [pts], 255)
    f = small.astype(np.float32) / 255; b, g, r = f[..., 0], f[..., 1], f[..., 2]
    mx = f.max(2); mn = f.min(2); sat = np.where(mx > 1e-6, (mx - mn) / np.maximum(mx, 1e-6), 0)
    valid = (R > 0) & ~(((mx > 0.8) & (sat < 0.25)) | (g > r * 1.05) | (b > r * 1.05))
    exc = ((~valid) & (R > 0)).astype(np.uint8) * 255
    valid &= cv2.dilate(exc, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))) == 0
    sm, sd = (tissue if robust else plain)(sat[valid]); vm, vd = plain(mx[valid])
    ves = ((sat > sm + 3 * sd) | (mx < vm - 3 * vd)).astype(np.uint8) * 255
    valid2 = valid & (cv2.dilate(ves, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))) == 0)
    ov = small.copy(); ov[(R > 0) & ~valid] = (255, 0, 0); ov[valid & ~valid2] = (0, 220, 255)
    vis = cv2.addWeighted(small, 0.45, ov, 0.55, 0); cv2.polylines(vis, [pts], True, (0, 255, 0), 1)
    return vis, valid2.sum() / (R > 0).sum()
if __name__ == '__main__':
    out = sys.argv[1]; rows = []
    for case in sys.argv[2:]:
        a, fa = mask(case, 600, False); b, fb = mask(case, 600, True)
        for im, t in ((a, 'before: kept %.0f %% of the ROI' % (100 * fa)), (b, 'after: kept %.0f %%' % (100 * fb))):
            cv2.putText(im, t, (10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2, cv2.LINE_AA)
        cv2.putText(a, case.split('/')[-2] + ' ' + case.split('/')[-1], (10, 60), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2, cv2.LINE_AA)
        rows.append(np.hstack([a, b]))
    cv2.imwrite(out, np.vstack(rows), [cv2.IMWRITE_JPEG_QUALITY, 85])
