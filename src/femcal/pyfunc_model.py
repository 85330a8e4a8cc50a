"""MLflow "model from code" entry point for femcal surrogates.

MLflow runs this file when it loads a logged femcal model, so the model is rebuilt from the
saved surrogate directory (weights + JSON config) rather than unpickled.
"""

import mlflow

from femcal.tracking import SurrogatePyfunc

mlflow.models.set_model(SurrogatePyfunc())
