"""femcal's experiments: the benchmarks behind the docs' measured figures.

Each ``bench_*`` module is a command (``python -m experiments.bench_diagnose --help``); the
experiments pipeline (``experiments/dvc.yaml``, ``experiments/params.yaml``) runs them and
writes their results to ``experiments/results/`` (DVC-tracked, not in git). The cohort
generators (:mod:`experiments.hidden_cohorts`) and the diagnosis harness
(:mod:`experiments.diagnosis`, :mod:`experiments.ceiling`, :mod:`experiments.diagnose_report`)
are shared by several benchmarks.

This package imports nothing itself: importing one experiment loads only what it uses.
"""
