"""Paired differences, masked_blur on the final stages only (masked_blur_max_fwhm_mm 3) minus the
plain blur, of every run: one column per set and test.

Reads final_stages_only_runs.csv beside this file, writes masked_blur_final.png (paired_picture.py
draws).
"""
import os
import sys

here = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(here))
from paired_picture import draw  # noqa: E402

draw(os.path.join(here, "final_stages_only_runs.csv"), "mre_variant_mm", os.path.join(here, "masked_blur_final.png"),
     "masked_blur on the FWHM 2 mm stages minus the plain blur")
