"""The open FE model of the L4-L5 disc on CalculiX (``ccx``): solver adapter ``"calculix"``.

Model
-----
Geometry and mesh: :mod:`femcal.fe.geometry` (elliptic cylinder 50 x 35 x 11 mm, nucleus 44 %
of the volume, annulus in ``n_rings`` rings x ``n_regions`` circumferential regions per side,
C3D20R elements). Units: mm, N, MPa. Axes: x lateral (to the right), y anterior, z cranial.

The bottom endplate is fixed (all translations of its nodes, i.e. a rigid, anchored caudal
endplate). The top endplate is a rigid body (``*RIGID BODY``) whose reference node lies
``reference_height_mm`` (10 mm) above the disc centre, as in the study. Loads on the rigid
body, ramped linearly over one static step (``NLGEOM``), with output exactly at each level
(``*TIME POINTS``):

============== ======================= =============================================
load case      load                    rotation reported (RoM)
============== ======================= =============================================
Flexion        moment -M about +x      -rotation about x (anterior side goes down)
Extension      moment +M about +x      +rotation about x
LateralBending moment +M about +y      +rotation about y (right side goes down)
AxialRotation  moment +M about +z      +rotation about z (counter-clockwise from above)
Compression    force -F along z        none (RoM is NaN)
============== ======================= =============================================

RoM is the rotation of the rigid top endplate about the load axis in the direction of the
applied moment, in degrees (positive when the disc turns the way it is pushed; flexion and
extension turn the disc in opposite directions about x), from the mesh's geometry or, with
``neutral_step``, from the neutral position: a first step without load, in which pre-strained
elements turn the unloaded disc, ends where the rotations are counted from. IDP is
``-mean(trace(sigma) / 3)`` of the Cauchy stress over all integration points of the central
nucleus elements (``CENTRAL``: the central O-grid block, layers nearest mid-height), in MPa.

Materials
---------
Nucleus: ``*HYPERELASTIC, MOONEY-RIVLIN`` with ``C10Nucleus``, ``C01Nucleus`` and a fixed
compressibility ``D1 = nucleus_d1`` (default 0.01 1/MPa, bulk modulus ``2 / D1`` = 200 MPa,
Poisson's ratio >= 0.4988 over the study's bounds; the study's ``D`` corresponds to
``1 / D1``).

Annulus: CalculiX's built-in anisotropic hyperelastic material ``ELASTIC_FIBER`` (one material
per ring x region, ``ELASTIC_FIBER_R{ring}C{region}``), energy
``C10 (I1bar - 3) + (J - 1)^2 / D1 + sum_f k1 / (2 k2) [exp(k2 <I4bar_f - 1>^2) - 1]`` with
``C10 = C10Annulus``, fixed ``D1 = annulus_d1`` (default 0.3 1/MPa) and two fibre families at
``+alpha`` and ``-alpha`` to the transverse (horizontal) plane, in the plane spanned by the
circumferential and the axial direction (the study's convention: the fibre angle is measured
from the transverse plane). The local axes of each annulus element (``*DISTRIBUTION``) are the
outward normal of the ellipse through its centre (radial), the ellipse's tangent
(circumferential) and +z; fibres do not carry compression.

Regional variation (the study's ``K1Circ``, ``K2Circ``, ``K1Rad``, ``K2Rad``,
``FiberAngleCirc``, ``FiberAngleRad``) is multiplicative and linear in a circumferential
coordinate ``c`` and a radial coordinate ``r``::

    k1(ring, region)    = K1Annulus  * (1 + K1Circ * c)         * (1 + K1Rad * r)
    k2(ring, region)    = K2Annulus  * (1 + K2Circ * c)         * (1 + K2Rad * r)
    alpha(ring, region) = FiberAngle * (1 + FiberAngleCirc * c) * (1 + FiberAngleRad * r)

with ``c = region / (n_regions - 1)`` in [0, 1] from the anterior (0) to the posterior (1)
region and ``r = ring / (n_rings - 1)`` in [0, 1] from the outer (0) to the inner (1) ring. So
with the study's bounds (``K*Circ``, ``K*Rad`` in [-0.2, 0]; ``FiberAngleCirc`` in [0, 0.3],
``FiberAngleRad`` in [0, 0.2]) the fibres are stiffest at the outer anterior annulus and get
softer posteriorly and inwards, and the fibre angle grows (up to 30 % and 20 %) towards the
posterior and inner annulus.

Fibre dispersion ``Kappa`` (not available in stock CalculiX), option ``kappa``:

``"scale"`` (default)
    small-strain equivalent of the Holzapfel-Gasser-Ogden dispersion: with
    ``E = kappa (I1bar - 3) + (1 - 3 kappa)(I4bar - 1)`` and ``I1bar - 3`` of second order in
    the strain, ``k1`` and ``k2`` are both multiplied by ``(1 - 3 kappa)^2``. This keeps the
    trend (more dispersion, softer fibres; isotropic at kappa = 1/3) but under-predicts the
    fibre stress at finite strain (by 18-48 % for kappa 0.1-0.3 in a feasibility probe).
``"ignore"``
    ``Kappa`` is accepted and has no effect (perfectly aligned fibres).

Failures and retries
--------------------
A run that does not reach every level is ``"failed"`` with the solver's ``*ERROR`` message as
the reason, and NaN outputs beyond the last level reached (earlier levels are kept). An abort
in the fibre routine ("fiber extension is too large for exponential function", exit code 201:
a Newton trial state of a too large increment, in the first increment or, for soft annulus
configurations, later) is retryable: attempt ``k`` uses the first increment
``min(initial_increment, first level) * retry_factor**k`` and up to ``max_increments * 4**k``
increments. CalculiX grows an increment only after fast convergence (fewer than 4 iterations
twice in a row), which these models rarely show, so a retry keeps small increments and costs
several times a first attempt. Any other failure (too many cutbacks, increment below the
minimum, increment limit) and a timeout are not retryable.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
import math
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np

from femcal.errors import ConfigError, SolverError
from femcal.fe.base import (
    COMPRESSION,
    FEJob,
    FEResult,
    PreparedRun,
    RunOutcome,
    register_solver,
)
from femcal.fe.calculix_settings import PosteriorSettings, posterior_settings
from femcal.fe.cpu_limit import CpuLimit
from femcal.fe.dat import read_dat
from femcal.fe.geometry import DiscGeometry, DiscMesh
from femcal.fe.materials import region_materials, validate_parameters
from femcal.fe.posterior import posterior_deck
from femcal.schema import PARAMETER_NAMES, STATUS_FAILED, STATUS_OK

logger = logging.getLogger(__name__)

#: File stem of the input deck (``disc.inp``) and of the solver's outputs (``disc.dat``, ...).
JOB_NAME = "disc"
#: Fix for a missing solver, quoted in errors.
INSTALL_HINT = "install it with `apt-get install calculix-ccx` or `make install`"
#: Log text of the fibre routine's abort (exit code 201), which a smaller increment avoids.
FIBRE_ABORT = "fiber extension is too large"

#: Largest time increment (fraction of the step); output times cut increments further.
MAX_INCREMENT = 0.25

#: Load case -> (rotation DOF of the moment (1 = x, 2 = y, 3 = z), sign of the moment).
MOMENT_AXES: dict[str, tuple[int, float]] = {
    "Flexion": (1, -1.0),
    "Extension": (1, 1.0),
    "LateralBending": (2, 1.0),
    "AxialRotation": (3, 1.0),
}

#: Environment for each solver run: one thread (campaigns run jobs side by side).
SINGLE_THREAD_ENV: dict[str, str] = {
    "OMP_NUM_THREADS": "1",
    "CCX_NPROC_EQUATION_SOLVER": "1",
    "CCX_NPROC_RESULTS": "1",
    "CCX_NPROC_STIFFNESS": "1",
}


def _fmt(value: float) -> str:
    return f"{value:.9g}"


def _data_lines(values: list[str], per_line: int = 8) -> list[str]:
    rows = [values[i : i + per_line] for i in range(0, len(values), per_line)]
    return [", ".join(row) + ("," if i < len(rows) - 1 else "") for i, row in enumerate(rows)]


def _id_lines(ids: np.ndarray, per_line: int = 16) -> list[str]:
    labels = [str(int(i) + 1) for i in ids]
    return [", ".join(labels[i : i + per_line]) for i in range(0, len(labels), per_line)]


@register_solver("calculix")
class CalculixDisc:
    """Solver adapter for the disc model on CalculiX (see the module docstring).

    Parameters
    ----------
    geometry : DiscGeometry, dict or str
        The geometry, a mesh preset name (``"coarse"``, ``"default"``, ``"fine"``) or a dict of
        :class:`DiscGeometry` fields (optionally with ``"preset"``).
    kappa : {"scale", "ignore"}
        Treatment of the fibre dispersion ``Kappa``.
    executable : str
        The CalculiX binary (name on ``PATH`` or path).
    initial_increment : float
        First time increment of the first attempt (fraction of the step, in (0, 1]).
    max_attempts : int
        Attempts of a job whose failure is retryable (fibre-routine abort).
    timeout_s : float or None
        CPU seconds (user + system) a run may use; a run over them is killed and failed
        (:class:`femcal.fe.cpu_limit.CpuLimit`: the machine's load does not decide it).
    max_increments : int
        Increment limit of the first attempt (times 4 on each retry).
    retry_factor : float
        The first increment is multiplied by this on each retry.
    nucleus_d1, annulus_d1 : float
        Compressibility ``D1`` (1/MPa) of the nucleus and the annulus ground substance.
    posterior : PosteriorSettings, mapping or None
        Posterior elements joined to the disc (:mod:`femcal.fe.posterior`): ``facets``
        and/or ``ligaments``; None (or none present): the disc alone, whose deck does not
        change with this setting.
    neutral_step : bool
        Start with a step without load and report every rotation from where it ends: the RoM
        from the neutral position, as a measurement is zeroed. Pre-strained elements (a
        ligament's negative slack strain) turn the unloaded disc; without this step their
        rotation at rest counts as RoM. False: rotations from the mesh's geometry.
    """

    name = "calculix"

    def __init__(
        self,
        *,
        geometry: DiscGeometry | dict | str = "default",
        kappa: str = "scale",
        executable: str = "ccx",
        initial_increment: float = 0.1,
        max_attempts: int = 3,
        timeout_s: float | None = None,
        max_increments: int = 100,
        retry_factor: float = 0.3,
        nucleus_d1: float = 0.01,
        annulus_d1: float = 0.3,
        posterior: PosteriorSettings | dict | None = None,
        neutral_step: bool = False,
    ) -> None:
        self.geometry = DiscGeometry.from_value(geometry)
        self.posterior = posterior_settings(posterior, where="CalculixDisc(posterior=...)")
        if kappa not in ("scale", "ignore"):
            raise ConfigError(f"kappa must be 'scale' or 'ignore', got {kappa!r}.")
        if not 0.0 < initial_increment <= 1.0:
            raise ConfigError(f"initial_increment must lie in (0, 1], got {initial_increment!r}.")
        if int(max_attempts) < 1 or int(max_increments) < 1:
            raise ConfigError("max_attempts and max_increments must be >= 1.")
        if not 0.0 < retry_factor <= 1.0:
            raise ConfigError(f"retry_factor must lie in (0, 1], got {retry_factor!r}.")
        if timeout_s is not None and not timeout_s > 0:
            raise ConfigError(f"timeout_s must be positive or None, got {timeout_s!r}.")
        for name, value in (("nucleus_d1", nucleus_d1), ("annulus_d1", annulus_d1)):
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a positive compressibility, got {value!r}.")
        self.kappa = kappa
        self.executable = executable
        self.initial_increment = float(initial_increment)
        self.max_attempts = int(max_attempts)
        self.timeout_s = timeout_s
        self.max_increments = int(max_increments)
        self.retry_factor = float(retry_factor)
        self.nucleus_d1 = float(nucleus_d1)
        self.annulus_d1 = float(annulus_d1)
        self.neutral_step = bool(neutral_step)
        self._mesh: DiscMesh | None = None
        self._mesh_text: str | None = None
        self._version: str | None = None

    # -- solver ---------------------------------------------------------------------------
    def _resolve_executable(self) -> str:
        path = shutil.which(self.executable)
        if path is None:
            raise SolverError(
                f"CalculiX executable {self.executable!r} not found (PATH or path); "
                f"{INSTALL_HINT}, or pass executable=<path to ccx>."
            )
        return path

    def version(self) -> str:
        """The CalculiX version (``ccx -v``), e.g. ``"2.20"``.

        Raises
        ------
        SolverError
            When the executable is missing or does not report a version.
        """
        if self._version is None:
            exe = self._resolve_executable()
            try:
                proc = subprocess.run(
                    [exe, "-v"], capture_output=True, text=True, timeout=30, check=False
                )
            except (OSError, subprocess.TimeoutExpired) as exc:
                raise SolverError(f"Cannot run {exe} -v ({exc}); {INSTALL_HINT}.") from exc
            match = re.search(r"Version\s+(\S+)", proc.stdout + proc.stderr)
            if not match:
                raise SolverError(
                    f"{exe} -v did not report a CalculiX version (output: "
                    f"{(proc.stdout + proc.stderr).strip()[:200]!r}); {INSTALL_HINT}."
                )
            self._version = match.group(1)
        return self._version

    # -- deck -----------------------------------------------------------------------------
    @property
    def mesh(self) -> DiscMesh:
        """The mesh of :attr:`geometry` (built once)."""
        if self._mesh is None:
            self._mesh = self.geometry.mesh()
        return self._mesh

    def _mesh_block(self) -> str:
        if self._mesh_text is not None:
            return self._mesh_text
        mesh = self.mesh
        lines = ["*NODE, NSET=NALL"]
        lines += [
            f"{i + 1}, {x:.10g}, {y:.10g}, {z:.10g}" for i, (x, y, z) in enumerate(mesh.nodes)
        ]
        lines.append("*ELEMENT, TYPE=C3D20R, ELSET=EALL")
        for i, conn in enumerate(mesh.elements + 1):
            labels = [str(i + 1), *(str(int(n)) for n in conn)]
            lines.append(", ".join(labels[:16]) + ",")
            lines.append(", ".join(labels[16:]))
        for name, ids in mesh.element_sets.items():
            lines.append(f"*ELSET, ELSET={name}")
            lines += _id_lines(ids)
        for name, ids in mesh.node_sets.items():
            lines.append(f"*NSET, NSET={name}")
            lines += _id_lines(ids)
        ref = mesh.n_nodes + 1
        rx, ry, rz = mesh.geometry.reference_point
        posterior = posterior_deck(
            self.posterior, mesh.node_sets["TOP"], ref + 2, mesh.n_elements + 1
        )
        lines += [
            "** Reference node (translations) and rotation node of the rigid top endplate",
            "*NODE, NSET=REFNODE",
            f"{ref}, {rx:.10g}, {ry:.10g}, {rz:.10g}",
            "*NODE, NSET=ROTNODE",
            f"{ref + 1}, {rx:.10g}, {ry:.10g}, {rz:.10g}",
            *posterior.lines,
            f"*RIGID BODY, NSET={posterior.rigid_set}, REF NODE={ref}, ROT NODE={ref + 1}",
            "*BOUNDARY",
            "BOTTOM, 1, 3",
            "** Local axes of the annulus elements: radial (normal to the ellipse), "
            "circumferential",
            "*DISTRIBUTION, NAME=ANNULUS_AXES",
            ", 1., 0., 0., 0., 1., 0.",
        ]
        axes = mesh.fibre_axes()
        for e in mesh.element_sets["ANNULUS"]:
            a, b = axes[e]
            lines.append(
                f"{e + 1}, {a[0]:.8f}, {a[1]:.8f}, {a[2]:.8f}, {b[0]:.8f}, {b[1]:.8f}, {b[2]:.8f}"
            )
        lines += ["*ORIENTATION, NAME=ANNULUS_OR", "ANNULUS_AXES"]
        self._mesh_text = "\n".join(lines) + "\n"
        return self._mesh_text

    def _material_block(self, parameters: dict[str, float]) -> str:
        g = self.geometry
        p = parameters
        lines = [
            "*MATERIAL, NAME=NUCLEUS",
            "*HYPERELASTIC, MOONEY-RIVLIN",
            f"{_fmt(p['C10Nucleus'])}, {_fmt(p['C01Nucleus'])}, {_fmt(self.nucleus_d1)}",
            "*SOLID SECTION, ELSET=NUCLEUS, MATERIAL=NUCLEUS",
        ]
        fibres = region_materials(p, g.n_rings, g.n_regions, self.kappa)
        for (ring, region), (k1, k2, alpha) in fibres.items():
            name = f"ELASTIC_FIBER_R{ring + 1}C{region + 1}"
            ny = math.cos(math.radians(alpha))
            constants = [p["C10Annulus"], self.annulus_d1, 0.0, ny, k1, k2, 0.0, -ny, k1, k2]
            lines += [
                f"** ring {ring + 1} (1 = outer), region {region + 1} (1 = anterior): "
                f"k1={_fmt(k1)}, k2={_fmt(k2)}, alpha={_fmt(alpha)} deg",
                f"*MATERIAL, NAME={name}",
                f"*USER MATERIAL, CONSTANTS={len(constants)}",
                *_data_lines([_fmt(v) for v in constants]),
                f"*SOLID SECTION, ELSET=A_R{ring + 1}C{region + 1}, MATERIAL={name}, "
                "ORIENTATION=ANNULUS_OR",
            ]
        return "\n".join(lines) + "\n"

    def _step_block(self, job: FEJob, attempt: int) -> tuple[str, dict]:
        levels = np.asarray(job.levels, dtype=float)
        times = levels / levels[-1]
        first = min(self.initial_increment, float(times[0])) * self.retry_factor**attempt
        max_inc = self.max_increments * 4**attempt
        static = [
            f"*STEP, NLGEOM, INC={max_inc}",
            "*STATIC",
            f"{_fmt(first)}, 1., {_fmt(min(1e-6, first))}, {_fmt(MAX_INCREMENT)}",
        ]
        lines = ["*TIME POINTS, NAME=LEVELS", *_data_lines([_fmt(t) for t in times])]
        if self.neutral_step:  # the unloaded disc settles; its rotation there is the zero
            lines += ["*TIME POINTS, NAME=NEUTRAL", "1."]
            lines += [*static, "*NODE PRINT, NSET=ROTNODE, TIME POINTS=NEUTRAL", "U", "*END STEP"]
        lines += static
        if job.load_case == COMPRESSION:
            lines += ["*CLOAD", f"REFNODE, 3, {_fmt(-levels[-1])}"]
        else:
            dof, sign = MOMENT_AXES[job.load_case]
            lines += ["*CLOAD", f"ROTNODE, {dof}, {_fmt(sign * levels[-1] * 1000.0)}"]
        lines += [
            "*NODE PRINT, NSET=ROTNODE, TIME POINTS=LEVELS",
            "U",
            "*EL PRINT, ELSET=CENTRAL, TIME POINTS=LEVELS",
            "S",
            "*END STEP",
        ]
        info = {
            "times": times.tolist(),
            "initial_increment": first,
            "max_increments": max_inc,
            "neutral_step": self.neutral_step,
        }
        return "\n".join(lines) + "\n", info

    def deck(self, job: FEJob, attempt: int = 0) -> tuple[str, dict]:
        """The input deck text of ``job`` and the settings of this attempt.

        Raises
        ------
        InputDataError
            When a parameter is missing, not finite or not admissible.
        """
        parameters = validate_parameters(job.parameters, where=f"FE job {job.key}")
        step, info = self._step_block(job, attempt)
        g = self.geometry
        header = [
            "*HEADING",
            f"femcal L4-L5 disc, job {job.key}, attempt {attempt}",
            "** units: mm, N, MPa; x lateral (right), y anterior, z cranial",
            f"** geometry: {g.to_dict()}",
            f"** kappa treatment: {self.kappa}; nucleus D1 {_fmt(self.nucleus_d1)}, "
            f"annulus D1 {_fmt(self.annulus_d1)}",
            *(f"** {name} = {_fmt(parameters[name])}" for name in PARAMETER_NAMES),
            f"** load case {job.load_case}, levels {[_fmt(v) for v in job.levels]}",
        ]
        if self.posterior.active:
            header.append(f"** posterior elements: {dataclasses.asdict(self.posterior)}")
        text = "\n".join(header) + "\n" + self._mesh_block()
        text += self._material_block(parameters) + step
        return text, info

    def prepare(self, job: FEJob, workdir: Path, attempt: int = 0) -> PreparedRun:
        """Write ``<workdir>/disc.inp`` for ``job`` (attempt ``k`` starts with a smaller step)."""
        workdir = Path(workdir)
        text, info = self.deck(job, attempt)
        workdir.mkdir(parents=True, exist_ok=True)
        for stale in workdir.glob(f"{JOB_NAME}.*"):
            stale.unlink()
        deck = workdir / f"{JOB_NAME}.inp"
        data = text.encode()
        deck.write_bytes(data)
        return PreparedRun(
            job=job,
            workdir=workdir,
            deck=deck,
            deck_hash=hashlib.sha256(data).hexdigest(),
            attempt=attempt,
            info=info,
        )

    # -- run ------------------------------------------------------------------------------
    def run(self, prepared: PreparedRun) -> RunOutcome:
        """Run ``ccx`` on the deck (one thread); CPU seconds of the child from ``wait4``."""
        exe = self._resolve_executable()
        env = {**os.environ, **SINGLE_THREAD_ENV}
        log_path = prepared.workdir / f"{JOB_NAME}.log"
        start = time.perf_counter()
        with open(log_path, "wb") as log:
            try:
                proc = subprocess.Popen(
                    [exe, "-i", JOB_NAME],
                    cwd=prepared.workdir,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    stdin=subprocess.DEVNULL,
                    env=env,
                )
            except OSError as exc:
                raise SolverError(f"Cannot start {exe} ({exc}); {INSTALL_HINT}.") from exc
            limit = CpuLimit(proc, self.timeout_s) if self.timeout_s else None
            with limit or contextlib.nullcontext():
                try:
                    _, status, usage = os.wait4(proc.pid, 0)
                except BaseException:
                    proc.kill()
                    proc.wait()
                    raise
        returncode = os.waitstatus_to_exitcode(status)
        proc.returncode = returncode
        wall = time.perf_counter() - start
        cpu = usage.ru_utime + usage.ru_stime
        prepared.info["timed_out"] = limit.reason if limit is not None else None
        tail = "\n".join(log_path.read_text(errors="replace").splitlines()[-40:])
        logger.debug(
            "ccx %s attempt %d: exit %d, %.1f s CPU, %.1f s wall",
            prepared.job.key,
            prepared.attempt,
            returncode,
            cpu,
            wall,
        )
        return RunOutcome(returncode=returncode, log_tail=tail, cpu_seconds=cpu, wall_seconds=wall)

    # -- parse ----------------------------------------------------------------------------
    def parse(self, prepared: PreparedRun, outcome: RunOutcome) -> FEResult:
        """RoM and IDP per level from ``disc.dat``; status, reason and retryability."""
        job = prepared.job
        times = np.asarray(prepared.info.get("times", np.asarray(job.levels) / job.levels[-1]))
        results = read_dat(prepared.workdir / f"{JOB_NAME}.dat")
        n = times.size
        rom = np.full(n, np.nan)
        idp = np.full(n, np.nan)

        def lookup(table: dict[float, object], t: float) -> object | None:
            for key, value in table.items():
                if abs(key - t) <= 1e-5 * max(1.0, abs(t)):
                    return value
            return None

        # The .dat file gives total times: after a neutral step (1.0), each level at 1 + t,
        # and the rotations from the neutral position are those less the rotation at 1.0.
        start = 1.0 if prepared.info.get("neutral_step") else 0.0
        zero = lookup(results.rotations, 1.0) if start else np.zeros(3)
        reached = 0
        for i, t in enumerate(times):
            pressure = lookup(results.idp, start + t)
            rotation = lookup(results.rotations, start + t)
            if pressure is None or rotation is None or zero is None:
                break
            idp[i] = float(pressure)
            if job.load_case != COMPRESSION:
                dof, sign = MOMENT_AXES[job.load_case]
                turned = float(np.asarray(rotation)[dof - 1]) - float(np.asarray(zero)[dof - 1])
                rom[i] = math.degrees(sign * turned)
            reached += 1

        log_path = prepared.workdir / f"{JOB_NAME}.log"
        log_text = log_path.read_text(errors="replace") if log_path.is_file() else outcome.log_tail
        timed_out = bool(prepared.info.get("timed_out"))
        errors = [line.strip() for line in log_text.splitlines() if "*ERROR" in line.upper()]
        retryable = False
        if reached == n and outcome.returncode == 0 and not timed_out:
            status, reason = STATUS_OK, ""
        else:
            status = STATUS_FAILED
            if timed_out:
                message = f"timeout after {prepared.info['timed_out']}"
            elif FIBRE_ABORT in log_text.lower():
                message = next(
                    (line.strip() for line in log_text.splitlines() if FIBRE_ABORT in line.lower()),
                    FIBRE_ABORT,
                )
                retryable = True
            elif errors:
                message = errors[0]
            elif outcome.returncode != 0:
                message = f"ccx exited with code {outcome.returncode}"
            else:
                message = "results missing in disc.dat"
            reason = (
                f"{message} (exit code {outcome.returncode}; {reached} of {n} levels reached; "
                f"attempt {prepared.attempt})"
            )
        return FEResult(
            job=job,
            status=status,
            reason=reason,
            rom_deg=rom,
            idp_mpa=idp,
            solver_version=self.version(),
            deck_hash=prepared.deck_hash,
            attempts=prepared.attempt + 1,
            cpu_seconds=outcome.cpu_seconds,
            wall_seconds=outcome.wall_seconds,
            retryable=retryable,
        )
