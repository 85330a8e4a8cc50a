"""The study's inverse-model baseline: RoM curves -> parameters in one pass.

Atad et al. ("Inverse model", after Liu et al. 2021 and Babaei et al. 2022): a feed-forward
ReLU network maps the 20 RoM values of a specimen (4 load cases x 5 moments, load case major
in the order of :data:`~femcal.schema.LOAD_CASES`) to the 13 parameters in the study's min-max
unit box, constrained to (0, 1) by a Sigmoid and trained with an MAE loss and
ReduceLROnPlateau on 50,000 configurations sampled in the box whose curves come from the NN
surrogate. The study reports it as fast (0.01 s for the Test set) but ill-posed: mean MAE
0.52 deg and mean R^2 0.54 on the synthetic Test specimens, because many configurations give
nearly the same curves.

The problem stays ill-posed in the parameters: the predicted configurations reproduce the
curves, while the parameters the curves do not determine are guesses. Its figures (fit,
parameter recovery, time) are on the docs' page *Benchmarks > Measurements behind the
defaults*.

Pieces:

* :mod:`femcal.inverse.net` - :class:`InverseNet`, the torch module (the input
  standardisation, of log RoM by default, lives in its buffers, so a saved network is the whole
  model), and :class:`InverseLightningModule`, which trains it (MAE, AdamW,
  ReduceLROnPlateau);
* :mod:`femcal.inverse.model` - :class:`InverseModel`, the scikit-learn style estimator
  (``fit``/``predict``/``save``/``load``; best validation weights restored);
* :mod:`femcal.inverse.data` - :func:`make_inverse_dataset`, the training set from the
  surrogate, and :func:`rom_mae_deg`;
* :mod:`femcal.inverse.train` - :func:`train_inverse`: the shared Optuna study runner
  (:mod:`femcal.training.study`), the final model logged as an MLflow pyfunc and registered;
* :mod:`femcal.inverse.store` - :func:`log_inverse` and :func:`load_inverse`, the registered
  model or the ``models/inverse`` folder back as an :class:`InverseModel`;
* the ``inverse`` calibrator is :mod:`femcal.calibration.inverse`.

The network only understands the full grid it was trained on; specimens with missing points or
another moment grid must use a fitting calibrator (``--method pgd``).
"""

from femcal.inverse.data import SAMPLINGS, make_inverse_dataset, rom_mae_deg
from femcal.inverse.model import STUDY_SETTINGS, InverseModel
from femcal.inverse.net import InverseLightningModule, InverseNet
from femcal.inverse.store import (
    DEFAULT_INVERSE_NAME,
    DEFAULT_INVERSE_URI,
    load_inverse,
    log_inverse,
)
from femcal.inverse.train import InverseTrainResult, inverse_kwargs, train_inverse

__all__ = [
    "DEFAULT_INVERSE_NAME",
    "DEFAULT_INVERSE_URI",
    "SAMPLINGS",
    "STUDY_SETTINGS",
    "InverseLightningModule",
    "InverseModel",
    "InverseNet",
    "InverseTrainResult",
    "inverse_kwargs",
    "load_inverse",
    "log_inverse",
    "make_inverse_dataset",
    "rom_mae_deg",
    "train_inverse",
]
