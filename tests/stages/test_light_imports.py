"""Calibrating imports no training library: Lightning, Optuna and LightGBM load only to train.

``femcal calibrate`` spends most of its wall time importing; the calibrate stage, the neural
surrogate it loads, the calibrators and the model store must not pull the training stack.
"""

from __future__ import annotations

import subprocess
import sys

TRAINING_ONLY = ("pytorch_lightning", "lightning", "optuna", "lightgbm")


def test_the_calibrate_path_imports_no_training_library():
    code = (
        "import sys\n"
        "import femcal.stages.calibrate, femcal.stages.diagnose, femcal.surrogates.nn\n"
        "import femcal.calibration.pgd, femcal.tracking, femcal.effects.composite\n"
        f"print(sorted(m for m in {TRAINING_ONLY!r} if m in sys.modules))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]", proc.stdout


def test_training_still_brings_lightning():
    """The check can fail: the training module does import Lightning."""
    code = (
        "import sys, femcal.surrogates.romnet_training\nprint('pytorch_lightning' in sys.modules)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.stdout.strip() == "True", proc.stderr
