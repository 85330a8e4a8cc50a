"""Constants shared by the calibration tests."""

from __future__ import annotations

#: The moment policy's settings the stage tests run with (params.yaml ``moments``).
MOMENTS = {"error_growth": 3.2, "max_log_ratio": 0.51}
