"""Reading the results CalculiX writes to its .dat file (rotations, pressures per step)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

_HEADER = re.compile(
    r"^\s*(?P<kind>displacements|stresses)\b.*?\bfor set\s+(?P<set>\S+)\s+and time\s+"
    r"(?P<time>\S+)",
    re.IGNORECASE,
)


_FORTRAN_EXPONENT = re.compile(r"(?<=[0-9.])([+-]\d{2,3})$")


@dataclass
class DatResults:
    """What :func:`read_dat` finds in a CalculiX ``.dat`` file.

    Attributes
    ----------
    rotations : dict of float to ndarray of shape (3,)
        Time -> rotation vector of the rigid body's rotation node in radians.
    idp : dict of float to float
        Time -> ``-mean(trace(sigma) / 3)`` over the printed integration points, in MPa.
    """

    rotations: dict[float, np.ndarray]
    idp: dict[float, float]


def _to_float(token: str) -> float:
    try:
        return float(token)
    except ValueError:
        # Fortran drops the "E" of three-digit exponents: 0.1234567-100.
        return float(_FORTRAN_EXPONENT.sub(r"E\1", token))


def read_dat(path: Path, rotation_set: str = "ROTNODE", stress_set: str = "CENTRAL") -> DatResults:
    """Read the rotation-node displacements and central stresses of a ``.dat`` file.

    Parameters
    ----------
    path : Path
        The solver's ``.dat`` file (missing file: no results).
    rotation_set, stress_set : str
        Node set of the rotation node and element set of the IDP elements.

    Returns
    -------
    DatResults
    """
    rotations: dict[float, np.ndarray] = {}
    stresses: dict[float, list[list[float]]] = {}
    path = Path(path)
    if not path.is_file():
        return DatResults(rotations, {})
    current: tuple[str, str, float] | None = None
    for line in path.read_text(errors="replace").splitlines():
        header = _HEADER.match(line)
        if header:
            current = (
                header["kind"].lower(),
                header["set"].upper(),
                _to_float(header["time"]),
            )
            continue
        fields = line.split()
        if current is None or not fields:
            continue
        kind, name, t = current
        try:
            values = [_to_float(v) for v in fields]
        except ValueError:
            current = None
            continue
        if kind == "displacements" and name == rotation_set.upper() and len(values) >= 4:
            rotations[t] = np.array(values[1:4])
        elif kind == "stresses" and name == stress_set.upper() and len(values) >= 8:
            stresses.setdefault(t, []).append(values[2:8])
    idp = {t: float(-np.mean(np.asarray(s)[:, :3].sum(axis=1) / 3.0)) for t, s in stresses.items()}
    return DatResults(rotations, idp)
