"""Neural-network surrogate of the RoM: a differentiable torch model trained with Lightning.

Architecture (:class:`RomNet`): for one configuration the RoM curve of a load case is very close
to a cubic polynomial in the log-moment in log-RoM space (a least-squares cubic in ``log M``
reproduces the study's Test curves to 0.0007 deg MAE). The network therefore maps the 13
parameters (unit box; parameters whose bounds are strictly positive in log scale) through an
MLP to the 4 x 4 coefficients of those cubics; a row ``(load case, moment, parameters)`` is
evaluated as ``RoM = exp(y_loc + y_scale * sum_j c_j(params, load case) * z**j)`` with
``z = (log M - m_loc) / m_scale``. This is the surrogate of the contract (one RoM per row,
any moment > 0), exactly differentiable in the parameters, and it trains on configurations
rather than rows: 20 times fewer MLP evaluations per epoch than a row-wise MLP on the study's
grid, at equal accuracy per epoch.

Its accuracy and training time on the study's Test set are on the docs' page *Benchmarks >
Surrogates and calibration*.

Normalisation lives in two places only: the :class:`~femcal.space.ParameterSpace` bounds and
the buffers of the fitted :class:`RomNet` (bounds, moment and output scaling).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import torch

from femcal import errors
from femcal.errors import ConfigError, InputDataError
from femcal.schema import LOAD_CASES
from femcal.space import ParameterSpace
from femcal.surrogates.base import check_features, error_profile, register_surrogate
from femcal.surrogates.contract import RegressorContract
from femcal.surrogates.romnet import (
    ACTIVATIONS,  # noqa: F401 (re-exported: the activations NeuralSurrogate takes)
    LOSSES,
    LR_SCHEDULES,
    RomNet,
    check_activation,
)
from femcal.training import persist

if TYPE_CHECKING:
    import pytorch_lightning as pl

log = logging.getLogger(__name__)

_FORMAT = "femcal-nn"
_FORMAT_VERSION = 1
_PREDICT_BATCH = 65_536


# ------------------------------------------------------------------------------ surrogate
@register_surrogate("nn")
class NeuralSurrogate(RegressorContract):
    """Neural-network RoM surrogate (scikit-learn's estimator contract, without importing it:
    :class:`~femcal.surrogates.contract.RegressorContract`).

    Defaults are the measured best recipe for the study's Large set (one member ~50 s on one
    CPU thread; use ``n_members=5`` for the best accuracy).

    Parameters
    ----------
    space : ParameterSpace
        Parameter names and bounds (the columns of ``X`` besides load_case and moment_nm).
    hidden : sequence of int
        Hidden-layer widths of each member MLP.
    activation : {"gelu", "silu", "relu", "tanh", "softplus"}
        Hidden activation.
    log_target : bool
        Model log RoM (RoM must then be > 0).
    loss : {"l1", "l2"}
        Training loss on the scaled (log-)RoM.
    learning_rate : float
        Peak learning rate (AdamW, one-cycle schedule over ``max_epochs``).
    weight_decay : float
        AdamW weight decay.
    batch_size : int
        Configurations (distinct parameter vectors, all their rows) per optimisation step.
    max_epochs : int
        Epochs per member.
    patience : int
        Early stopping: epochs without a better ``val_mae_deg`` (the best weights are restored
        at the end in any case).
    dropout : float
        Dropout after each hidden activation.
    n_members : int
        Ensemble size; member ``k`` is seeded ``seed + k``.
    val_fraction : float
        Fraction of configurations held out for validation when ``X_val`` is not given
        (0 trains on everything, without early stopping).
    seed : int
        Seed of the validation split, the initial weights and the batch order.
    log_params : bool
        Parameters with strictly positive bounds enter the network in log scale.
    lr_schedule : {"onecycle", "cosine", "constant"}
        Learning-rate schedule.
    warm_start : bool
        As in scikit-learn: a fitted model's next ``fit`` starts each member from its current
        weights and keeps its output and moment scalings (fine-tuning on new FE runs, e.g.
        with a smaller ``learning_rate`` and ``max_epochs`` set by ``set_params``); the
        architecture and ``n_members`` must then be unchanged. False: every fit starts anew.
    moment_degree : int, optional
        Degree of each curve's polynomial in log-moment (None: 3, which reproduces the
        study's 1..5 Nm curves to 0.0007 deg). A wider moment range needs more: on the FE
        campaign's 0.5..10 Nm curves a least-squares cubic in log-moment misses by 0.025 deg
        on average (0.11 deg at the 95th percentile), degree 6 by 0.0062 (0.042)
        (``experiments/bench_fe_curve_form.py``). Capped by the number of distinct training
        moments minus one.

    Attributes
    ----------
    net_ : RomNet
        The fitted ensemble, eval mode.
    history_ : list of dict
        One dict per member and epoch: member, epoch, train_loss, val_loss, val_mae_deg.
    best_val_mae_deg_ : float
        MAE in degrees of the ensemble on the validation rows (NaN without validation).
    n_features_in_ : int
        2 + d: load_case, moment_nm and the d parameters.
    moment_range_ : tuple of float
        Smallest and largest training moment in Nm (the range the surrogate interpolates in).
    val_error_profile_ : dict or None
        The ensemble's error on the validation rows by training moment:
        ``{"moments": [...], "rms_deg": [...], "relative_rms": [...]}`` (Nm, deg, 1; root mean
        square over the rows at each moment, all load cases, of the error and of the error
        over the prediction), which :meth:`femcal.moments.MomentPolicy.for_surrogate`
        reads as the surrogate's error sd inside the trained range. None without validation.
    """

    def __init__(
        self,
        space: ParameterSpace,
        *,
        hidden: Sequence[int] = (256, 256, 256, 256),
        activation: str = "gelu",
        log_target: bool = True,
        loss: str = "l1",
        learning_rate: float = 3e-3,
        weight_decay: float = 0.0,
        batch_size: int = 64,
        max_epochs: int = 800,
        patience: int = 100,
        dropout: float = 0.0,
        n_members: int = 1,
        val_fraction: float = 0.15,
        seed: int = 0,
        log_params: bool = True,
        lr_schedule: str = "onecycle",
        warm_start: bool = False,
        moment_degree: int | None = None,
    ) -> None:
        self.space = space
        self.hidden = hidden
        self.activation = activation
        self.log_target = log_target
        self.loss = loss
        self.learning_rate = learning_rate
        self.weight_decay = weight_decay
        self.batch_size = batch_size
        self.max_epochs = max_epochs
        self.patience = patience
        self.dropout = dropout
        self.n_members = n_members
        self.val_fraction = val_fraction
        self.seed = seed
        self.log_params = log_params
        self.lr_schedule = lr_schedule
        self.warm_start = warm_start
        self.moment_degree = moment_degree

    # --------------------------------------------------------------------- helpers
    def _init_args(self) -> dict[str, Any]:
        args = self.get_params(deep=False)
        args.pop("space")
        args["hidden"] = [int(h) for h in args["hidden"]]
        return args

    def _check_settings(self) -> None:
        check_activation(self.activation)
        if self.loss not in LOSSES:
            raise ConfigError(f"Unknown loss '{self.loss}'; choose one of {', '.join(LOSSES)}.")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ConfigError(
                f"Unknown lr_schedule '{self.lr_schedule}'; choose one of "
                f"{', '.join(LR_SCHEDULES)}."
            )
        ints = {"batch_size": self.batch_size, "max_epochs": self.max_epochs}
        ints.update(n_members=self.n_members, patience=self.patience)
        bad = [f"{k}={v}" for k, v in ints.items() if int(v) < (0 if k == "patience" else 1)]
        md = self.moment_degree
        if md is not None and (
            isinstance(md, bool) or not isinstance(md, int | np.integer) or not 0 <= md <= 8
        ):
            raise ConfigError(
                f"NeuralSurrogate: moment_degree must be an integer in 0..8 (the degree of each "
                f"curve's polynomial in log-moment) or None (3); got {self.moment_degree!r}."
            )
        if bad or not 0.0 <= float(self.val_fraction) < 1.0 or not 0.0 <= self.dropout < 1.0:
            raise ConfigError(
                f"Invalid NeuralSurrogate settings ({', '.join(bad) or 'see fractions'}): need "
                "batch_size, max_epochs, n_members >= 1, patience >= 0, 0 <= val_fraction < 1 "
                "and 0 <= dropout < 1."
            )

    def _rows(self, X: pd.DataFrame, what: str = "X") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Validated columns: load-case index (n,), moment (n,), physical params (n, d)."""
        check_features(X, self.space, what=what)
        lc = pd.Categorical(X["load_case"].astype(str), categories=list(LOAD_CASES)).codes
        moment = X["moment_nm"].to_numpy(dtype=float)
        params = X[list(self.space.names)].to_numpy(dtype=float)
        if np.any(~(moment > 0)) or not np.all(np.isfinite(moment)):
            raise InputDataError(
                f"{what}: moment_nm must be finite and > 0 (the network uses log moment); "
                "drop the 0 Nm rows (RoM 0 by definition)."
            )
        if not np.all(np.isfinite(params)):
            raise InputDataError(f"{what}: parameters must be finite numbers.")
        return lc.astype(np.int64), moment, params

    def _targets(self, y: Any, n: int, what: str) -> np.ndarray:
        y = np.asarray(y, dtype=float).reshape(-1)
        if y.size != n:
            raise InputDataError(f"{what} has {y.size} values for {n} rows; give one RoM per row.")
        if not np.all(np.isfinite(y)):
            raise InputDataError(f"{what}: RoM must be finite; drop failed simulations first.")
        if self.log_target and np.any(y <= 0):
            raise InputDataError(
                f"{what}: log_target=True needs RoM > 0; drop the 0 Nm rows or set "
                "log_target=False."
            )
        return y

    def _split(self, X: pd.DataFrame, params: np.ndarray) -> np.ndarray:
        """Boolean validation mask over rows, by configuration, shape (n,)."""
        if "config_id" in X.columns:
            groups = pd.factorize(X["config_id"])[0]
        else:
            groups = np.unique(params, axis=0, return_inverse=True)[1].reshape(-1)
        n_groups = int(groups.max()) + 1
        n_val = int(round(float(self.val_fraction) * n_groups))
        n_val = min(max(n_val, 1), n_groups - 1) if self.val_fraction > 0 and n_groups > 1 else 0
        rng = np.random.default_rng(self.seed)
        val_groups = rng.permutation(n_groups)[:n_val]
        return np.isin(groups, val_groups)

    @staticmethod
    def _moment_degree(moment: np.ndarray, most: int = 3) -> int:
        """Degree of the log-moment polynomial: cubic, or lower when the training data has too
        few distinct moments to determine it (3 moments -> quadratic)."""
        distinct = int(np.unique(np.round(moment, 9)).size)
        degree = max(0, min(most, distinct - 1))
        if degree < most:
            log.info(
                "Only %d distinct training moments: using a degree-%d polynomial in log-moment.",
                distinct,
                degree,
            )
        return degree

    def _check_fitted(self) -> None:
        if not hasattr(self, "net_"):
            # looked up when raised: the error class imports scikit-learn (its NotFittedError)
            raise errors.SurrogateNotFittedError(
                f"This {type(self).__name__} is not fitted yet: call fit(X, y) or "
                "NeuralSurrogate.load(path) first."
            )

    def _warm_start_members(self, arch: dict[str, Any]) -> list[dict] | None:
        """The fitted members' weights to start from (``warm_start``), else None."""
        if not (self.warm_start and hasattr(self, "net_")):
            return None
        fitted = self.net_.architecture()
        want = {**arch, "n_members": int(self.n_members)}
        changed = [
            k
            for k in ("hidden", "activation", "n_members", "log_target", "log_params")
            if fitted[k] != want[k]
        ]
        if self.moment_degree is not None and fitted["moment_degree"] != want["moment_degree"]:
            changed.append("moment_degree")
        if changed:
            raise ConfigError(
                f"warm_start continues the fitted network, but {', '.join(changed)} changed "
                f"(fitted: {', '.join(f'{k}={fitted[k]}' for k in changed)}); restore them, or "
                "set warm_start=False to train anew."
            )
        return [{k: v.clone() for k, v in m.state_dict().items()} for m in self.net_.members]

    # ------------------------------------------------------------------------- fit
    def fit(
        self,
        X: pd.DataFrame,
        y: np.ndarray,
        *,
        X_val: pd.DataFrame | None = None,
        y_val: np.ndarray | None = None,
        logger: Any = None,
        callbacks: Sequence[pl.Callback] = (),
        progress: bool = False,
    ) -> NeuralSurrogate:
        """Train the ensemble.

        Parameters
        ----------
        X : DataFrame, n rows
            Columns load_case, moment_nm (> 0) and the parameter names (physical units); an
            optional config_id column defines the configurations of the validation split
            (otherwise rows with identical parameters form a configuration).
        y : array_like, shape (n,)
            RoM in degrees.
        X_val, y_val : DataFrame (m rows) and array_like (m,), optional
            Validation data; when omitted, ``val_fraction`` of the configurations of ``X``.
        logger : Lightning logger, optional
            Passed to every member's Trainer (e.g. an MLFlowLogger); None disables logging.
        callbacks : sequence of Lightning callbacks
            Extra callbacks (e.g. an Optuna pruning callback) for every member's Trainer.
        progress : bool
            Show Lightning's progress bar.

        Returns
        -------
        NeuralSurrogate
            ``self``.
        """
        # Lightning is imported only to train: loading and calibrating never need it.
        from femcal.surrogates.romnet_training import RomLightningModule, pack_blocks
        from femcal.training.lightning import batch_loader, fit_on_cpu, quiet_lightning

        self._check_settings()
        lc, moment, params, y, vlc, vmom, vpar, vy = self._training_rows(X, y, X_val, y_val)
        has_val = len(vy) > 0

        scales, arch = self._scales_and_architecture(moment, y)
        start = self._warm_start_members(arch)
        if start is not None:  # the fitted model's scalings: its weights are in their units
            net0 = self.net_
            scales = {k: float(getattr(net0, k)) for k in scales}
            arch["moment_degree"] = net0.moment_degree

        def scaled(values: np.ndarray) -> np.ndarray:
            tv = np.log(values) if self.log_target else values
            return (tv - scales["y_loc"]) / scales["y_scale"]

        train_blocks = pack_blocks(lc, moment, params, y, scaled(y))
        val_blocks = pack_blocks(vlc, vmom, vpar, vy, scaled(vy)) if has_val else None
        n_blocks = int(train_blocks[0].shape[0])
        n_batches = max(1, math.ceil(n_blocks / int(self.batch_size)))

        history: list[dict[str, Any]] = []
        states: list[dict[str, torch.Tensor]] = []
        with quiet_lightning():
            for k in range(int(self.n_members)):
                member_seed = int(self.seed) + k
                with torch.random.fork_rng(devices=[]):
                    torch.manual_seed(member_seed)
                    net = RomNet(self.space.lower, self.space.upper, n_members=1, **arch, **scales)
                    if start is not None:
                        net.members[0].load_state_dict(start[k])
                    module = RomLightningModule(
                        net,
                        loss=self.loss,
                        learning_rate=self.learning_rate,
                        weight_decay=self.weight_decay,
                        lr_schedule=self.lr_schedule,
                    )
                    gen = torch.Generator().manual_seed(member_seed)
                    train_loader = batch_loader(train_blocks, int(self.batch_size), gen)
                    val_loader = None
                    if val_blocks is not None:  # one batch: all validation blocks
                        val_loader = batch_loader(val_blocks, int(val_blocks[0].shape[0]), None)
                    fit_on_cpu(
                        module,
                        train_loader,
                        val_loader,
                        monitor="val_mae_deg",
                        patience=int(self.patience),
                        max_epochs=int(self.max_epochs),
                        n_batches=n_batches,
                        logger=logger,
                        callbacks=callbacks,
                        progress=progress,
                    )
                states.append(net.members[0].state_dict())
                history.extend({"member": k, **row} for row in module.history)
                last = module.history[-1] if module.history else {}
                log.debug("nn member %d: %d epochs, last %s", k, len(module.history), last)

        ens = RomNet(
            self.space.lower, self.space.upper, n_members=int(self.n_members), **arch, **scales
        )
        for member, state in zip(ens.members, states):
            member.load_state_dict(state)
        self.net_ = persist.freeze(ens)
        self.history_ = history
        self.n_features_in_ = 2 + self.space.dim
        self.moment_range_ = (float(np.min(moment)), float(np.max(moment)))
        if has_val:
            pred = self._predict_rows(vlc, vmom, vpar)
            self.record_validation_error(vmom, pred - vy, pred)
        else:
            self.best_val_mae_deg_ = math.nan
            self.val_error_profile_ = None
        return self

    def record_validation_error(
        self, moments: np.ndarray, error: np.ndarray, prediction: np.ndarray | None = None
    ) -> NeuralSurrogate:
        """Set ``best_val_mae_deg_`` and ``val_error_profile_`` from held-out rows.

        ``fit`` calls it on its validation rows; a fit without them (e.g. a fine-tuning on
        every row) calls it on rows held out elsewhere.

        Parameters
        ----------
        moments : ndarray, shape (n,)
            The rows' moments, Nm.
        error : ndarray, shape (n,)
            Prediction minus truth, deg.
        prediction : ndarray, shape (n,), optional
            The predictions, deg (the relative error by moment is recorded with them).
        """
        self.best_val_mae_deg_ = float(np.nanmean(np.abs(error)))
        self.val_error_profile_ = error_profile(moments, error, prediction)
        return self

    def _training_rows(
        self,
        X: pd.DataFrame,
        y: np.ndarray,
        X_val: pd.DataFrame | None,
        y_val: np.ndarray | None,
    ) -> tuple[np.ndarray, ...]:
        """The checked training and validation rows of :meth:`fit`: load-case index, moment
        (Nm), parameters (rows, d, physical units) and RoM (deg), training rows first.

        Without ``X_val``/``y_val``, ``val_fraction`` of the configurations of ``X`` are held
        out (:meth:`_split`).
        """
        lc, moment, params = self._rows(X)
        y = self._targets(y, len(lc), "y")
        if (X_val is None) != (y_val is None):
            raise InputDataError("Give both X_val and y_val, or neither.")
        if X_val is not None:
            vlc, vmom, vpar = self._rows(X_val, what="X_val")
            vy = self._targets(y_val, len(vlc), "y_val")
        else:
            val = self._split(X, params)
            train = ~val
            vlc, vmom, vpar, vy = lc[val], moment[val], params[val], y[val]
            lc, moment, params, y = lc[train], moment[train], params[train], y[train]
        return lc, moment, params, y, vlc, vmom, vpar, vy

    def _scales_and_architecture(
        self, moment: np.ndarray, y: np.ndarray
    ) -> tuple[dict[str, float], dict[str, Any]]:
        """The input and target scalings of a new :class:`RomNet` from the training moments
        (Nm) and RoM (deg), shape (rows,) each, and its architecture keywords."""
        t = np.log(y) if self.log_target else y
        y_loc, y_scale = float(t.mean()), float(t.std())
        log_m = np.log(moment)
        m_loc, m_scale = float(log_m.mean()), float(log_m.std())
        scales = {
            "moment_loc": m_loc,
            "moment_scale": m_scale if m_scale > 1e-12 else 1.0,
            "y_loc": y_loc,
            "y_scale": y_scale if y_scale > 1e-12 else 1.0,
        }
        arch = {
            "hidden": [int(h) for h in self.hidden],
            "activation": self.activation,
            "dropout": float(self.dropout),
            "log_target": bool(self.log_target),
            "log_params": bool(self.log_params),
            "moment_degree": self._moment_degree(
                moment, 3 if self.moment_degree is None else int(self.moment_degree)
            ),
        }
        return scales, arch

    # --------------------------------------------------------------------- predict
    def _predict_rows(self, lc: np.ndarray, moment: np.ndarray, params: np.ndarray) -> np.ndarray:
        out = np.empty(len(lc), dtype=np.float64)
        with torch.no_grad():
            for s in range(0, len(lc), _PREDICT_BATCH):
                sl = slice(s, s + _PREDICT_BATCH)
                out[sl] = (
                    self.net_(
                        torch.tensor(lc[sl]),
                        torch.tensor(moment[sl], dtype=torch.float32),
                        torch.tensor(params[sl], dtype=torch.float32),
                    )
                    .double()
                    .numpy()
                )
        return out

    def predict(self, X: pd.DataFrame) -> np.ndarray:
        """RoM in degrees.

        Parameters
        ----------
        X : DataFrame, n rows
            Columns load_case, moment_nm (> 0) and the parameter names, physical units.

        Returns
        -------
        ndarray of float64, shape (n,)
        """
        self._check_fitted()
        lc, moment, params = self._rows(X)
        return self._predict_rows(lc, moment, params)

    def torch_module(self) -> RomNet:
        """The fitted :class:`RomNet` (shared, eval mode, weights with requires_grad False).

        Call it with ``(load_case_index (n,), moment_nm (n,), params (n, d) physical)``; it is
        float32, use ``copy.deepcopy(m).double()`` for float64.
        """
        self._check_fitted()
        return self.net_

    # ------------------------------------------------------------------------- I/O
    def save(self, path: str | Path) -> None:
        """Write ``config.json`` (settings, space, architecture, fit summary) and ``weights.pt``.

        Parameters
        ----------
        path : Path
            Directory to create or overwrite.
        """
        self._check_fitted()
        config = {
            "format": _FORMAT,
            "version": _FORMAT_VERSION,
            "init": self._init_args(),
            "space": self.space.to_dict(),
            "architecture": self.net_.architecture(),
            "fitted": {
                "best_val_mae_deg": persist.finite_or_none(self.best_val_mae_deg_),
                "n_features_in": self.n_features_in_,
                "moment_range": list(self.moment_range_),
                "val_error_profile": getattr(self, "val_error_profile_", None),
                "history": persist.history_to_json(self.history_),
            },
        }
        persist.save_model_files(path, config, self.net_)

    @classmethod
    def load(cls, path: str | Path) -> NeuralSurrogate:
        """Read a surrogate written by :meth:`save`.

        Parameters
        ----------
        path : Path
            Directory with ``config.json`` and ``weights.pt``.

        Returns
        -------
        NeuralSurrogate
            Fitted, ready to predict.
        """
        config = persist.read_config(path, fmt=_FORMAT, what="NeuralSurrogate")
        space = ParameterSpace.from_dict(config["space"])
        init = dict(config["init"])
        init["hidden"] = tuple(init["hidden"])
        model = cls(space, **init)
        net = RomNet(space.lower, space.upper, **config["architecture"])
        state = persist.load_weights(path)
        net.load_state_dict(state)
        fitted = config.get("fitted", {})
        bv = fitted.get("best_val_mae_deg")
        model.net_ = persist.freeze(net)
        model.best_val_mae_deg_ = float(persist.none_to_nan(bv))
        model.n_features_in_ = int(fitted.get("n_features_in", 2 + space.dim))
        # Models saved before moment_range was recorded were all trained on 1..5 Nm.
        model.moment_range_ = tuple(float(v) for v in fitted.get("moment_range", (1.0, 5.0)))
        model.history_ = persist.history_from_json(fitted.get("history", []))
        model.val_error_profile_ = fitted.get("val_error_profile")
        return model
