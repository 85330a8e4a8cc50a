"""MLflow "model from code" entry point of every femcal model (surrogates, inverse model).

MLflow runs this file when it loads a logged femcal model, so the model is rebuilt from the
saved folder (weights + JSON config) rather than unpickled; see :mod:`femcal.training.pyfunc`.
"""

import mlflow

from femcal.training.pyfunc import FemcalPyfunc

mlflow.models.set_model(FemcalPyfunc())
