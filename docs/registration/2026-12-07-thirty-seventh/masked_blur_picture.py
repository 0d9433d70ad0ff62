"""Paired differences, masked_blur minus the defaults, of every run: one column per set and test.

Reads masked_blur_runs.csv beside this file, writes masked_blur.png (paired_picture.py draws).
"""
import os
import sys

here = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(here))
from paired_picture import draw  # noqa: E402

draw(os.path.join(here, "masked_blur_runs.csv"), "mre_masked_blur_mm", os.path.join(here, "masked_blur.png"),
     "masked_blur minus the defaults")
