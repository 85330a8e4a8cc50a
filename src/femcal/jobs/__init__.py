"""The two jobs a user runs on a measurement file, as library functions.

- :func:`femcal.jobs.calibrate.run_calibration`: what ``femcal calibrate`` does
  (:mod:`femcal.stages.calibrate`);
- :func:`femcal.jobs.diagnose.run_diagnosis`: what ``femcal diagnose`` does
  (:mod:`femcal.stages.diagnose`).

Each takes one frozen options object (:class:`~femcal.jobs.calibrate.CalibrationJob`,
:class:`~femcal.jobs.diagnose.DiagnosisJob`), built by hand or from a loaded params.yaml
(``from_params(params, **given)``: the file's settings, ``given`` winning), writes the same
output folder as the command and logs the same MLflow run, in the store and experiment MLflow
is pointed at. The stages parse the command line, build the options and call these.

Importing this package and its modules is light: torch, MLflow and the calibrators load when a
job runs.
"""
