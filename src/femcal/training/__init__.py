"""The training toolkit shared by every trained model (the surrogate and the inverse model).

* :mod:`femcal.training.study` - the Optuna study runner: an RDB storage with heartbeats
  (a killed study resumes), the known recipe enqueued as trial 0, every trial a nested MLflow
  run;
* :mod:`femcal.training.lightning` - Lightning helpers: the batch loader, best-weights
  keeping, Optuna pruning, the MLflow logger, a CPU trainer and quiet logging;
* :mod:`femcal.training.persist` - a fitted model as ``config.json`` + ``weights.pt``;
* :mod:`femcal.training.pyfunc` - the MLflow "model from code" wrapper and its logging
  (the entry point MLflow runs is :file:`pyfunc_model.py` beside it).

Nothing is imported here, so that importing one module does not import the others.
"""
