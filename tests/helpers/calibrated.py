"""A saved gallery with a known confidence: a copy of a gallery folder plus a calibration.json written by hand."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from geoloc.eval.calibration import Calibrator

# P(top-1 right) = sigmoid(4 * score + 10 * margin - 2), for queries of a given heading at fov 360
KNOWN = Calibrator("top1", ("top1_score", "top1_margin"), [0.0, 0.0], [1.0, 1.0], [4.0, 10.0], -2.0,
                   {"heading": "given", "fov": 360.0}, {"answers": 100, "right": 40, "rule": "by hand"})


def calibrated_copy(folder: Path, dest: Path, calibrator: Calibrator = KNOWN) -> Path:
    """`folder`'s gallery copied to `dest`, with calibrator as its top-1 confidence."""
    shutil.copytree(folder, dest)
    (dest / "calibration.json").write_text(json.dumps({"calibrated": True,
                                                       "targets": {"top1": calibrator.to_json()}}))
    return dest
