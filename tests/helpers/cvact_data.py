"""A CVACT ACT_data.mat in the released structure, for reader tests."""

from __future__ import annotations

import numpy as np
from scipy.io import savemat


def write_act_mat(root, ids, train, val):
    savemat(root / "ACT_data.mat", {
        "panoIds": np.array(ids, dtype=object),
        "trainSet": {"trainInd": np.array(train, dtype=np.float64).reshape(-1, 1)},
        "valSet": {"valInd": np.array(val, dtype=np.float64).reshape(-1, 1)},
        "valSetAll": {"valInd": np.array(val, dtype=np.float64).reshape(-1, 1)},
        "utm": np.zeros((len(ids), 2)),
    })
