"""Constants and markers shared by the FE tests."""

from __future__ import annotations

import shutil

import pytest

MOMENTS = (1.0, 2.0, 3.0, 4.0, 5.0)
COARSE = {"geometry": "coarse"}
SPLITS = {"large": 1, "small": 1, "test": 1}

requires_ccx = pytest.mark.skipif(
    shutil.which("ccx") is None, reason="CalculiX (ccx) is not installed; `make install`"
)
