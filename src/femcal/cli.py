"""``femcal`` command line: parses the arguments, runs a stage, prints what it says.

Every DVC stage is one sub-command, e.g. ``femcal train --split large``, run by its module in
:mod:`femcal.stages` (settings from params.yaml and the command line, then ``run``). ``-v``
logs femcal's debug messages, ``-q`` only its warnings (and hides the progress bars, which are
shown on a terminal only); ``--version`` prints the installed version. torch, OpenMP and BLAS
run on the cores free when the command starts (:mod:`femcal.threads`); ``OMP_NUM_THREADS``,
``MKL_NUM_THREADS`` or ``OPENBLAS_NUM_THREADS`` set by the user wins.

Relative paths typed on the command line start at the current folder; relative paths in
params.yaml start at its folder (the project root), and the stores' (``mlflow.store_dir``,
``train.storage``) at the repository's root, also in the temporary copy of ``dvc exp run
--temp/--queue`` (:mod:`femcal.paths`).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import warnings
from importlib import metadata
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

from femcal.config import load_params
from femcal.errors import FemcalError, FemcalWarning
from femcal.settings import unwrap
from femcal.settings.keywords import BUILTIN_EFFECTS, CALIBRATOR_NAMES, PLOT_CHOICES, SPLITS
from femcal.stages import settings_class, stage_module
from femcal.threads import limit_threads
from femcal.tracking_runs import tag_runs_with_stage

#: Logging level of the ``femcal`` logger per verbosity option (none given: INFO).
LOG_LEVELS = {"verbose": logging.DEBUG, "default": logging.INFO, "quiet": logging.WARNING}


def version() -> str:
    """The installed femcal's version (the package metadata; the source's when not installed)."""
    try:
        return metadata.version("femcal")
    except metadata.PackageNotFoundError:  # pragma: no cover - run from a source tree
        from femcal import __version__

        return __version__


def configure_logging(level: int) -> None:
    """Route log records to stderr; femcal logs at ``level``, other libraries from WARNING.

    ``-v`` (DEBUG) also lets other libraries' INFO records through. femcal's own warnings
    (:class:`~femcal.errors.FemcalWarning`) are logged where they arise: one line each, not
    printed again as a ``UserWarning`` with its source line.
    """
    warnings.filterwarnings("ignore", category=FemcalWarning)
    logging.basicConfig(
        level=logging.INFO if level <= logging.DEBUG else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    logging.getLogger("femcal").setLevel(level)


def _progress(args: argparse.Namespace) -> bool:
    """Progress bars: on a terminal (stderr) only, and not with ``-q``."""
    return sys.stderr.isatty() and args.log_level < LOG_LEVELS["quiet"]


#: MLflow's switch of its artifact progress bars ("Downloading artifacts", "Uploading ...").
MLFLOW_PROGRESS_VARIABLE = "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR"


def configure_mlflow_progress(progress: bool) -> None:
    """MLflow's artifact progress bars where femcal shows its own only (:func:`_progress`):
    off when stderr is no terminal (``dvc repro``, a log file) or with ``-q``.

    A value the user set in :data:`MLFLOW_PROGRESS_VARIABLE` is kept.
    """
    if not progress:
        os.environ.setdefault(MLFLOW_PROGRESS_VARIABLE, "false")


def _add_metrics_file(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--metrics-file",
        metavar="PATH",
        help="also write the summary figures to this JSON file (the DVC stage passes its "
        "metrics file, e.g. reports/diagnose.json; an ad-hoc run leaves those untouched)",
    )


def _add_compare_to(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--compare-to",
        metavar="RUN_OR_FOLDER",
        help="write comparison.md against this earlier calibration: its output folder or its "
        "MLflow run id (default: the latest earlier run of the same file with the disc alone; "
        "comparison.md and the log say which)",
    )


def _add_effects_module(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--effects-module",
        action="append",
        metavar="PATH",
        help="a .py file (or folder of them) that registers effects; repeatable (also: "
        "effects.modules in params.yaml)",
    )


def _add_verbosity(p: argparse.ArgumentParser, *, default: object) -> None:
    """``-v/--verbose`` and ``-q/--quiet``, exclusive; given before or after the sub-command."""
    group = p.add_mutually_exclusive_group()
    group.add_argument(
        "-v",
        "--verbose",
        dest="log_level",
        action="store_const",
        const=LOG_LEVELS["verbose"],
        default=default,
        help="also log femcal's debug messages (and other libraries' info)",
    )
    group.add_argument(
        "-q",
        "--quiet",
        dest="log_level",
        action="store_const",
        const=LOG_LEVELS["quiet"],
        default=default,
        help="log warnings and errors only; no progress bars",
    )


#: The params.yaml settings each command reads, which it takes on its command line: section ->
#: its keys (None: all), one option each, ``--<key>`` (``_`` as ``-``), its help the setting's
#: doc (:func:`_add_settings`).
SETTINGS_OF: dict[str, dict[str, tuple[str, ...] | None]] = {
    "calibrate": {"calibrate": None, "moments": None},
    "diagnose": {"diagnose": None, "moments": None, "calibrate": ("start_bank",)},
}
#: Options whose choices argparse lists (a plugin calibrator is a choice too).
_CHOICES = {("calibrate", "method"): CALIBRATOR_NAMES}
_SETTINGS = "settings_given"  # a command's settings options: destination -> (section, key)


def _reader(annotation: Any, path_like: bool) -> Any:
    """Reads an option's text as YAML (``3``, ``0.05``, ``null``, ``{pgd: {n_starts: 16}}``);
    for a list, ``a,b`` too; a relative path starts at the current folder."""
    tp = unwrap(annotation)[0]
    listy = tuple in {get_origin(unwrap(a)[0]) for a in (tp, *get_args(tp))}

    def read(text: str) -> Any:
        import yaml

        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:
            value = text
        if listy and isinstance(value, str):
            value = [item.strip() for item in value.split(",") if item.strip()]
        if path_like and isinstance(value, str):
            value = str(Path(value).absolute())
        return value

    return read


def _add_settings(p: argparse.ArgumentParser, command: str) -> None:
    """One option per setting ``command`` reads (:data:`SETTINGS_OF`) that ``p`` has no option
    for yet, declared by the section's field (and so by the options dataclass it reads): same
    name, same doc."""
    given = {}
    for section, keys in SETTINGS_OF[command].items():
        given.update(_add_section(p, section, keys))
    p.set_defaults(**{_SETTINGS: given})


def _add_section(
    p: argparse.ArgumentParser, section: str, keys: tuple[str, ...] | None
) -> dict[str, tuple[str, str]]:
    """The options of ``section``'s settings ``keys`` (None: all): destination -> (section,
    key)."""
    from femcal.settings import SECTIONS, describe, fields_of, keys_of
    from femcal.settings.values import PATH

    model, added = SECTIONS[section][0], {}
    for key, name in keys_of(model).items():
        flag = "--" + key.replace("_", "-")
        if keys is not None and key not in keys or flag in p._option_string_actions:
            continue
        field = fields_of(model)[name]
        tp = field.rebuild_annotation()
        choices = _CHOICES.get((section, key))
        words = describe(tp)
        p.add_argument(
            flag,
            dest=key,
            default=argparse.SUPPRESS,
            choices=choices,
            type=str if choices else _reader(tp, PATH in (tp, *get_args(tp))),
            metavar=None if choices else "PATH" if PATH in (tp, *get_args(tp)) else _metavar(tp),
            help=f"{field.description}; {words} (default: {section}.{key} in params.yaml)".replace(
                "%", "%%"
            ),
        )
        added[key] = (section, key)
    return added


def _metavar(annotation: Any) -> str:
    """``N``, ``X``, ``{true,false}``, ``A,B,...``, ``PATH``, ``TEXT`` or ``YAML``."""
    tp = unwrap(annotation)[0]
    inner = [unwrap(a)[0] for a in get_args(tp) if a is not type(None)] or [tp]
    tp = tp if get_origin(tp) in (tuple, dict, Literal) else inner[0]
    names = {int: "N", float: "X", bool: "{true,false}", str: "TEXT"}
    if get_origin(tp) is Literal:
        return "{" + ",".join(map(str, get_args(tp))) + "}"
    return "A,B,..." if get_origin(tp) is tuple else names.get(tp, "YAML")


def setting_overrides(args: argparse.Namespace) -> dict[tuple[str, ...], tuple[str, Any]]:
    """The settings given on the command line: (section, key) -> (option, value)."""
    return {
        path: ("--" + dest.replace("_", "-"), getattr(args, dest))
        for dest, path in getattr(args, _SETTINGS, {}).items()
        if hasattr(args, dest)
    }


def _add_shared(p: argparse.ArgumentParser, section: str) -> None:
    """The options ``calibrate`` and ``diagnose`` share: the file, the output folder, the
    noise, the surrogate, the metrics file and the user's effects."""
    p.add_argument(
        "--measurements",
        help=f"measurement file: a long or wide CSV, or a folder of the study's "
        f"files (default: {'calibrate.datasets.<name>' if section == 'calibrate' else section}"
        ".measurements)",
    )
    # diagnose's --out is its setting diagnose.out_dir: one option under both names; calibrate's
    # is the folder of one dataset, inside calibrate.out_dir (its own --out-dir).
    p.add_argument(
        *(("--out",) if section == "calibrate" else ("--out", "--out-dir")),
        dest="out",
        help=f"output folder (default: {section}.out_dir"
        + ("/<dataset>)" if section == "calibrate" else " in params.yaml)"),
    )
    p.add_argument("--model-uri", help="MLflow model URI or folder (default: calibrate.model_uri)")
    _add_metrics_file(p)
    _add_effects_module(p)


_EPILOG = {
    "calibrate": (
        "example:\n  femcal calibrate --measurements data/my.csv --effects facet_contact "
        "--out reports/my\n\n"
        "writes to the output folder: parameters.csv, metrics.csv, ranges.csv, curves.csv, "
        "summary.md,\nsummary.json, summary.png, plots/<specimen>.png, comparison.md/.json, "
        "dropped_points.csv\n(docs/reference/outputs.md); --metrics-file: the DVC metrics"
    ),
    "diagnose": (
        "example:\n  femcal diagnose --measurements data/my.csv --candidates "
        "facet_contact,neutral_zone --alpha 0.05\n\n"
        "writes to the output folder: diagnosis.json, residuals.csv, summary.md, summary.json,\n"
        "heatmap.png, plots/<specimen>.png, dropped_points.csv (docs/reference/outputs.md); "
        "--metrics-file: the DVC metrics"
    ),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="femcal", description=__doc__.splitlines()[0].replace("``", "")
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    parser.add_argument(
        "--params",
        default="params.yaml",
        help="settings file (default: params.yaml). Relative paths in it start at its folder "
        "(the project root), whatever the current folder; the stores (mlflow.store_dir, "
        "train.storage, fe.store) at the repository's root, also from the temporary copy of "
        "`dvc exp run --temp/--queue` (DVC_ROOT); MLFLOW_TRACKING_URI and FEMCAL_OPTUNA_STORAGE "
        "override them. Relative paths given on the command line start at the current folder",
    )
    _add_verbosity(parser, default=LOG_LEVELS["default"])
    # The sub-commands take -v/-q too; given there, they win (absent, they leave the top's).
    common = argparse.ArgumentParser(add_help=False)
    _add_verbosity(common, default=argparse.SUPPRESS)
    sub = parser.add_subparsers(dest="command", required=True)

    def command(name: str, **kwargs) -> argparse.ArgumentParser:
        return sub.add_parser(name, parents=[common], **kwargs)

    p = command("fetch", help="get the study's FE data (mirror or pinned download)")
    p.add_argument("--out", help="destination folder (default: data.raw_dir)")
    command("prepare", help="tidy tables + parameter space")
    for name, helptext in (
        ("train", "Optuna search + final surrogate, logged and registered in MLflow"),
        ("baselines", "fit the study's model zoo"),
    ):
        command(name, help=helptext)
    sub.choices["train"].add_argument(
        "--split",
        required=True,
        help="a section of train in params.yaml (large, small, holdout, ...); it names the run, "
        "and its `split` setting the prepared table trained on (one of "
        f"{', '.join(SPLITS)}; default: the section's name)",
    )
    _add_metrics_file(sub.choices["train"])
    sub.choices["baselines"].add_argument(
        "--split", required=True, choices=SPLITS, help="the prepared table to fit on"
    )
    command("interpolate", help="train on 1,3,5 Nm, test at 2,4 Nm")
    command("evaluate", help="Test-set table for every surrogate")
    command(
        "train-inverse", help="the study's inverse network on surrogate samples (Optuna, MLflow)"
    )
    p = command(
        "calibrate",
        help="calibrate measured specimens (registered surrogate)",
        epilog=_EPILOG["calibrate"],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_shared(p, "calibrate")
    p.add_argument("--dataset", help="a name under calibrate.datasets (default: the first)")
    p.add_argument(
        "--effects",
        metavar="EFFECT[,EFFECT...]",
        help="comma-separated physical effects added to the disc (default: the dataset's "
        "effects in params.yaml; none for --measurements); '' = the disc alone. Built in: "
        f"{', '.join(BUILTIN_EFFECTS)}; installed plugins and --effects-module files add more",
    )
    p.add_argument(
        "--noise-deg",
        type=float,
        help="sd of one measurement in degrees: each point weighs 1 / (noise² / weight + the "
        "surrogate's error²), as in diagnose, and each specimen is tested against it "
        "(metrics.csv: rms_z, p_value, flag 'beyond noise') (default: "
        "calibrate.datasets.<name>.noise_deg, not for --measurements; none: only the "
        "surrogate's error is counted; the output names the source)",
    )
    p.add_argument("--model-version", help="version of the registered surrogate")
    p.add_argument("--model-alias", help="alias of the registered surrogate")
    p.add_argument("--holdout-uri", help="held-out surrogate URI (default: calibrate.holdout_uri)")
    p.add_argument("--no-holdout", action="store_true", help="skip the held-out re-evaluation")
    p.add_argument(
        "--plots",
        choices=PLOT_CHOICES,
        help="figures to write: all (plots/<specimen>.png for the first calibrate.max_plots "
        "specimens, and summary.png), summary (summary.png only) or none; the tables, "
        "curves.csv and summary.md/json are always written (default: calibrate.plots, "
        "true = all, false = none)",
    )
    _add_compare_to(p)
    _add_settings(p, "calibrate")
    command("plant", help="a cohort with hidden effects from FE curves")
    p = command(
        "diagnose",
        help="where the model fails; which effect is missing",
        epilog=_EPILOG["diagnose"],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_shared(p, "diagnose")
    p.add_argument(
        "--noise-deg",
        type=float,
        help="sd of one measurement in degrees (default: diagnose.noise_deg in params.yaml when "
        "set, else estimated with its uncertainty from the residuals of the disc alone, which "
        "count physics the disc lacks too; the output names the source)",
    )
    _add_settings(p, "diagnose")
    p = command("simulate", help="FE campaign on Dask -> dataset in the study's layout")
    p.add_argument("--out", help="dataset folder (default: fe.out_dir)")
    p.add_argument("--store", help="campaign store, .jsonl or .jsonl.gz (default: fe.store)")
    p.add_argument(
        "--retry-timeouts",
        action="store_true",
        help="run the stored jobs that failed on their time limit again",
    )
    _add_metrics_file(p)
    p = command("adapt", help="adaptive FE sampling; fine-tuned challenger vs the champion")
    _add_metrics_file(p)
    p = command("validate", help="FE re-simulation of calibrated parameters; IDP check")
    p.add_argument("--calibration", help="calibration folder (default: validate.calibration_dir)")
    p.add_argument("--measurements", help="measurements calibrated to (validate.measurements)")
    p.add_argument("--out", help="output folder (default: validate.out_dir)")
    p.add_argument("--store", help="campaign store of the FE runs (default: validate.store)")
    _add_metrics_file(p)
    return parser


def dispatch(args: argparse.Namespace, params: dict) -> None:
    """Run the stage of ``args.command``: its settings from params.yaml and the command line
    (checked there, before anything heavy is imported), then ``run``; print what it says."""
    module = stage_module(args.command)
    values = vars(args) | {"progress": _progress(args)}
    settings = settings_class(module).from_params(params, values)
    for line in module.describe(module.run(settings)):
        print(line)


def main(argv: list[str] | None = None) -> int:
    """Run the command ``argv`` (None: ``sys.argv[1:]``); its exit code (2: a femcal error).

    Called without ``argv`` (the ``femcal`` program, ``python -m femcal``), the process ends
    here once the command is done (:func:`exit_now`): torch's, pandas' and matplotlib's
    modules are not torn down one by one, which takes longer than many commands' own work.
    """
    code = run_command(argv)
    if argv is None:
        exit_now(code)
    return code


def exit_now(code: int) -> None:
    """End the process with ``code`` without the interpreter's teardown of every module
    (about 0.3 CPU-s with torch loaded): the ``atexit`` functions run first and the output
    streams are flushed, as at a normal exit. Returns (and the interpreter exits as usual)
    while a thread other than the main one is still running (its work is not cut short) and
    under a profiler or tracer (``python -m cProfile -o FILE -m femcal ...`` writes FILE once
    the command returns)."""
    import atexit
    import threading

    if sys.getprofile() is not None or sys.gettrace() is not None:
        return
    main_thread = threading.main_thread()
    if any(t is not main_thread and not t.daemon and t.is_alive() for t in threading.enumerate()):
        return
    atexit._run_exitfuncs()  # logging.shutdown and every function registered
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed or broken pipe: nothing more to say
            pass
    os._exit(code)


def run_command(argv: list[str] | None = None) -> int:
    """Parse ``argv``, run its stage and print what it says; the exit code (2: a femcal
    error, printed on stderr)."""
    args = build_parser().parse_args(argv)
    configure_logging(args.log_level)
    configure_mlflow_progress(_progress(args))
    try:
        # the command line's settings merged in, then validated against femcal.settings' schema
        params = load_params(args.params, overrides=setting_overrides(args))
        from femcal.settings import check_environment

        check_environment(args.command)  # the variables this command reads
        limit_threads()  # the cores free now, before torch starts its threads
        with tag_runs_with_stage(args.command):  # every MLflow run of the command, nested too
            dispatch(args, params)
    except FemcalError as exc:
        print(f"femcal {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
