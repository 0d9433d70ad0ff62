# Over-exposes a copy of a phantom set by two thirds of a stop (linear light x 1.6, clipped,
# re-encoded as the camera would), for the red-against-grey check in docs/registration.md:
#   cp -r ev8 ev8hot && python3 overexpose.py ev8hot
#   cortexfuse evaluate ev8hot --limit-cases 4 --trials 10 [--params grey_channel.json]
import cv2, glob, sys
import numpy as np
for ph in sorted(glob.glob(sys.argv[1] + '/case_*/photo.*')):
    im = cv2.imread(ph).astype(np.float32)
    lin = (im / 255.0) ** 2.2 * 1.6
    out = np.clip(lin ** (1 / 2.2) * 255, 0, 255).astype(np.uint8)
    cv2.imwrite(ph, out, [cv2.IMWRITE_JPEG_QUALITY, 90] if ph.endswith('.jpg') else [])
