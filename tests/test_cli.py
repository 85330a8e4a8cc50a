"""The command line: settings errors are clear, and exit with status 2; --version, -v/-q,
the choices in --help, progress bars only on a terminal."""

import logging
import os
import subprocess
import sys
from importlib import metadata

import pytest
import yaml

from femcal.cli import (
    MLFLOW_PROGRESS_VARIABLE,
    _progress,
    build_parser,
    configure_logging,
    configure_mlflow_progress,
    main,
)
from femcal.config import load_params, section
from femcal.errors import ConfigError
from femcal.settings import BUILTIN_EFFECTS, CALIBRATORS


def test_missing_params_file(tmp_path, capsys):
    assert main(["--params", str(tmp_path / "nope.yaml"), "prepare"]) == 2
    err = capsys.readouterr().err
    assert "nope.yaml does not exist; run from the project root or pass --params" in err


def test_missing_setting_names_key_and_file(tmp_path, capsys):
    p = tmp_path / "params.yaml"
    p.write_text("data: {raw_dir: raw}\n")
    assert main(["--params", str(p), "prepare"]) == 2
    assert "missing setting 'data.prepared_dir'" in capsys.readouterr().err


def test_invalid_yaml(tmp_path):
    p = tmp_path / "params.yaml"
    p.write_text("data: [unclosed\n")
    with pytest.raises(ConfigError, match="is not valid YAML"):
        load_params(p)


def test_non_mapping_yaml(tmp_path):
    p = tmp_path / "params.yaml"
    p.write_text("- a\n- b\n")
    with pytest.raises(ConfigError, match="must hold a mapping of sections; got list"):
        load_params(p)


def test_section_lookup(tmp_path):
    p = tmp_path / "params.yaml"
    p.write_text("train: {large: {n_trials: 3}}\n")
    params = load_params(p)
    assert section(params, "train", "large", "n_trials") == 3
    with pytest.raises(ConfigError, match="missing setting 'train.small'"):
        section(params, "train", "small", "n_trials")


def test_subcommands_exist():
    parser = build_parser()
    for cmd in (
        ["fetch"],
        ["prepare"],
        ["train", "--split", "large"],
        ["baselines", "--split", "small"],
        ["interpolate"],
        ["evaluate"],
        ["train-inverse"],
        ["calibrate", "--measurements", "m.csv", "--method", "ga", "--model-version", "2"],
    ):
        assert parser.parse_args(cmd).command == cmd[0]
    with pytest.raises(SystemExit):
        parser.parse_args(["train"])  # --split is required


def test_unknown_training_section_names_the_setting(tmp_path, capsys, monkeypatch):
    import mlflow

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    params = {
        "mlflow": {"store_dir": str(tmp_path / "mlruns"), "experiment": "t"},
        "train": {"storage": f"sqlite:///{tmp_path}/o.db"},
    }
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(params))
    try:
        code = main(["--params", str(tmp_path / "p.yaml"), "train", "--split", "medium"])
    finally:
        mlflow.set_tracking_uri(None)  # the command pointed MLflow at the temporary store
    assert code == 2
    assert "missing setting 'train.medium'" in capsys.readouterr().err


def test_fetch_and_prepare_from_a_mirror(tmp_path, monkeypatch, capsys, synthetic_raw_root):
    """fetch refuses a mirror whose files are not the study's (checksums), naming the fix."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("FEMCAL_DATA_MIRROR", str(synthetic_raw_root))
    (tmp_path / "params.yaml").write_text(
        "data: {raw_dir: data/raw, prepared_dir: data/prepared}\n"
    )
    assert main(["fetch"]) == 2
    err = capsys.readouterr().err
    assert "SHA-256" in err
    assert not (tmp_path / "data" / "raw" / "Large" / "MaterialConfigurations.csv").exists()


# ------------------------------------------------------------------ --version, -v, -q, --help
@pytest.fixture
def femcal_log_level():
    """main() sets the femcal logger's level: restore it for the other tests."""
    logger = logging.getLogger("femcal")
    level = logger.level
    yield logger
    logger.setLevel(level)


def test_version_prints_the_installed_version(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out == f"femcal {metadata.version('femcal')}\n"


@pytest.mark.parametrize(
    ("before", "after", "level"),
    [
        ([], [], logging.INFO),
        (["-v"], [], logging.DEBUG),
        (["--verbose"], [], logging.DEBUG),
        (["-q"], [], logging.WARNING),
        (["--quiet"], [], logging.WARNING),
        ([], ["-v"], logging.DEBUG),  # after the sub-command too
        (["-q"], ["--verbose"], logging.DEBUG),  # the sub-command's wins
    ],
)
def test_verbosity_sets_the_femcal_logger_level(tmp_path, femcal_log_level, before, after, level):
    argv = [*before, "--params", str(tmp_path / "nope.yaml"), "prepare", *after]
    assert main(argv) == 2
    assert femcal_log_level.level == level


def test_verbose_and_quiet_exclude_each_other(tmp_path, capsys):
    for argv in (["-v", "-q", "prepare"], ["prepare", "--quiet", "--verbose"]):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert "not allowed with argument" in err and "-v/--verbose" in err


@pytest.mark.parametrize(
    ("option", "shown", "hidden"),
    [
        ([], ["INFO femcal.probe: info"], ["debug"]),
        (["-v"], ["DEBUG femcal.probe: debug", "INFO femcal.probe: info"], []),
        (["-q"], ["WARNING femcal.probe: warning"], ["info", "debug"]),
    ],
)
def test_verbosity_changes_what_a_fresh_process_logs(tmp_path, option, shown, hidden):
    """The logging a command really gets: its records on stderr, by the option given."""
    code = (
        "import logging, sys\n"
        "from femcal.cli import main\n"
        "main(sys.argv[1:])\n"
        "log = logging.getLogger('femcal.probe')\n"
        "log.debug('debug'); log.info('info'); log.warning('warning')\n"
    )
    argv = [*option, "--params", str(tmp_path / "nope.yaml"), "prepare"]
    proc = subprocess.run(
        [sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120
    )
    lines = [line for line in proc.stderr.splitlines() if "femcal.probe" in line]
    assert lines[-1] == "WARNING femcal.probe: warning"
    for text in shown:
        assert text in lines
    for word in hidden:
        assert not any(line.endswith(f": {word}") for line in lines)


def _help(capsys, argv: list[str]) -> str:
    with pytest.raises(SystemExit) as exit_:
        main([*argv, "--help"])
    assert exit_.value.code == 0
    return " ".join(capsys.readouterr().out.split())  # unwrapped


def test_help_lists_the_choices(capsys):
    calibrate = _help(capsys, ["calibrate"])
    assert "--method {" + ",".join(CALIBRATORS) + "}" in calibrate
    assert f"Built in: {', '.join(BUILTIN_EFFECTS)};" in calibrate
    assert "--plots {all,summary,none}" in calibrate and "true = all, false = none" in calibrate
    assert "--split {large,small,test}" in _help(capsys, ["baselines"])
    assert "one of large, small, test" in _help(capsys, ["train"])
    for cmd in ("train", "calibrate", "diagnose"):
        assert "[-v | -q]" in _help(capsys, [cmd])
    top = _help(capsys, [])
    assert "-q, --quiet" in top and "--version" in top and "{fetch,prepare,train," in top


def test_an_unknown_choice_is_refused_with_the_choices(capsys):
    for argv, says in (
        (["calibrate", "--method", "lbfgs"], "argument --method: invalid choice: 'lbfgs'"),
        (["calibrate", "--plots", "some"], "argument --plots: invalid choice: 'some'"),
        (["baselines", "--split", "medium"], "argument --split: invalid choice: 'medium'"),
    ):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert says in err and "(choose from " in err


def test_version_and_help_answer_without_heavy_imports():
    code = (
        "import sys\n"
        "from femcal.cli import main\n"
        "for argv in (['--version'], ['calibrate', '--help'], ['train', '--help']):\n"
        "    try:\n"
        "        main(argv)\n"
        "    except SystemExit as exc:\n"
        "        assert exc.code == 0, exc.code\n"
        "heavy = [m for m in ('torch', 'pytorch_lightning', 'lightning', 'mlflow', 'optuna',"
        " 'sklearn', 'pandas') if m in sys.modules]\n"
        "print('HEAVY', heavy)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "HEAVY []"


def test_progress_bars_only_on_a_terminal_and_not_when_quiet(monkeypatch):
    parser = build_parser()
    master, replica = os.openpty()  # a real terminal for stderr
    with open(replica, "w") as terminal, open(os.devnull, "w") as devnull:
        monkeypatch.setattr(sys, "stderr", terminal)
        assert _progress(parser.parse_args(["prepare"]))
        assert _progress(parser.parse_args(["-v", "prepare"]))
        assert not _progress(parser.parse_args(["prepare", "-q"]))
        monkeypatch.setattr(sys, "stderr", devnull)  # a file or pipe (dvc repro, CI)
        assert not _progress(parser.parse_args(["prepare"]))
    os.close(master)


def test_mlflow_progress_bars_are_off_without_a_terminal(tmp_path, monkeypatch):
    """``dvc repro`` logs: no "Downloading artifacts" bars when stderr is no terminal."""
    from mlflow.environment_variables import MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR

    monkeypatch.setenv(MLFLOW_PROGRESS_VARIABLE, "x")
    monkeypatch.delenv(MLFLOW_PROGRESS_VARIABLE)  # restored after the test
    assert MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR.get() is True  # MLflow's default
    main(["--params", str(tmp_path / "nope.yaml"), "prepare"])  # stderr: no terminal here
    assert MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR.get() is False
    monkeypatch.delenv(MLFLOW_PROGRESS_VARIABLE)
    configure_mlflow_progress(True)  # a terminal: MLflow's own default
    assert MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR.get() is True
    monkeypatch.setenv(MLFLOW_PROGRESS_VARIABLE, "true")
    configure_mlflow_progress(False)  # the user's choice wins
    assert MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR.get() is True


def test_a_moment_warning_is_one_log_line_on_the_command_line(caplog):
    """The moment policy's warnings: one log line each, not also a UserWarning with its
    source line."""
    import warnings
    from types import SimpleNamespace

    import numpy as np

    from femcal.measurements import from_arrays
    from femcal.moments import MomentPolicy

    surrogate = SimpleNamespace(moment_range_=(1.0, 5.0), best_val_mae_deg_=0.024)
    policy = MomentPolicy.for_surrogate(surrogate, growth=3.2, max_log_ratio=0.51)
    m = np.array([1.0, 2.0, 7.5, 12.0])
    meas = from_arrays(["A"], m, np.broadcast_to(m, (1, 4, 4)).copy(), source="far.csv")
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        configure_logging(logging.INFO)
        with caplog.at_level(logging.WARNING, logger="femcal"):
            policy.screen(meas)
    logged = [r.getMessage() for r in caplog.records if r.name == "femcal.moments"]
    assert len(logged) == 2  # the dropped points, the points beyond the trained range
    assert "far.csv: dropped 4 measured point(s) at moments 12 Nm" in logged[0]
    assert [str(w.message) for w in shown] == []


def test_every_run_a_command_starts_is_tagged_with_its_stage(tmp_path, monkeypatch):
    """Nested runs too (an evaluation's per-model runs), so the MLflow UI groups them all."""
    import mlflow

    import femcal.cli

    monkeypatch.setenv("MLFLOW_RUN_CONTEXT", '{"mine": "kept"}')
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    started = []

    def dispatch(args, params):
        mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
        # an experiment of this store: the process may hold another store's active experiment
        mlflow.set_experiment("tagged")
        with mlflow.start_run(run_name="evaluate") as parent:
            with mlflow.start_run(run_name="eval-nn-large", nested=True) as child:
                started.extend([parent.info.run_id, child.info.run_id])

    monkeypatch.setattr(femcal.cli, "dispatch", dispatch)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        assert main(["--params", os.path.join(root, "params.yaml"), "evaluate"]) == 0
        tags = [mlflow.get_run(run_id).data.tags for run_id in started]
    finally:
        mlflow.set_tracking_uri(None)
    assert [t.get("femcal.stage") for t in tags] == ["evaluate", "evaluate"]
    assert all(t.get("mine") == "kept" for t in tags)
    assert os.environ["MLFLOW_RUN_CONTEXT"] == '{"mine": "kept"}'  # as before the command


@pytest.mark.parametrize("background", [False, True])
def test_the_program_ends_without_tearing_its_modules_down(tmp_path, background):
    """``femcal`` (main without argv) ends the process once the command is done: the atexit
    functions run and the output is flushed, the interpreter's teardown is skipped; a thread
    still working keeps the normal exit (it is not cut short)."""
    code = (
        "import atexit, sys, threading\n"
        "class Probe:\n"
        "    def __del__(self):\n"
        "        print('TORN DOWN', flush=True)\n"
        "probe = Probe()\n"
        "atexit.register(print, 'ATEXIT')\n"
        "done = threading.Event()\n"
        f"if {background}:  # a thread working until main has returned\n"
        "    threading.Thread(target=done.wait, args=(600,)).start()\n"
        f"sys.argv = ['femcal', '--params', {str(tmp_path / 'nope.yaml')!r}, 'prepare']\n"
        "from femcal.cli import main\n"
        "print('RETURNED', main(), flush=True)\n"
        "done.set()\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    out = proc.stdout.split()
    assert proc.returncode == (0 if background else 2), proc.stderr
    assert "femcal prepare: error:" in proc.stderr and "ATEXIT" in out
    if background:  # returned; the interpreter waits for the thread and exits as usual
        assert "RETURNED" in out and "TORN DOWN" in proc.stdout
    else:
        assert "RETURNED" not in out and "TORN DOWN" not in proc.stdout


def test_a_profiled_program_returns_to_its_profiler(tmp_path):
    """Under ``python -m cProfile -o FILE -m femcal``, the command returns to the profiler,
    which writes FILE."""
    stats = tmp_path / "femcal.prof"
    argv = ["--params", str(tmp_path / "nope.yaml"), "prepare"]
    proc = subprocess.run(
        [sys.executable, "-m", "cProfile", "-o", str(stats), "-m", "femcal", *argv],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert "femcal prepare: error:" in proc.stderr  # (cProfile's own exit status: 0)
    assert stats.stat().st_size > 0
