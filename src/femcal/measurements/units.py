"""Units of measured moments: a curve given in N·mm beside curves in Nm.

femcal reads moments in Nm (field ``moment_nm``). A file given wholly in N·mm is refused by
the moment policy (:meth:`femcal.moments.MomentPolicy.screen`), whose message names N·mm; a
file in which only some curves are in N·mm is refused here, before the policy would drop their
points as beyond the moments the surrogate is used at.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from femcal.errors import InputDataError, listed
from femcal.schema import LOAD_CASES

if TYPE_CHECKING:  # pragma: no cover
    from femcal.measurements import Measurements

#: Measured moments all at least this large look like N·mm rather than Nm.
NMM_THRESHOLD = 100.0
#: Most values or names a message lists.
_MAX_LISTED = 6


def _fmt(values: Sequence[float] | np.ndarray) -> str:
    return listed([f"{float(x):g}" for x in values], most=_MAX_LISTED)


def refuse_mixed_units(meas: Measurements, measured: np.ndarray) -> None:
    """Refuse a file in which some curves' moments look like N·mm beside others in Nm.

    A curve (specimen x load case) whose measured moments are all at least
    :data:`NMM_THRESHOLD` while another curve of the file has a moment below it was given in
    N·mm: its points would otherwise be dropped as beyond the surrogate's moments.

    Raises
    ------
    InputDataError
        Naming the file, the field, the load cases and specimens, their moments and the fix.
    """
    moments = np.asarray(meas.moments, dtype=float)
    curves = measured.any(axis=2)  # (n, 4)
    big = np.where(measured, moments[None, None, :] >= NMM_THRESHOLD, True).all(axis=2) & curves
    if not big.any() or (big == curves).all():  # none, or the whole file (refused elsewhere)
        return
    cases = []
    for k in np.flatnonzero(big.any(axis=0)):
        who = [meas.specimens[i] for i in np.flatnonzero(big[:, k])]
        names = (
            f"all {len(who)} specimens"
            if big[:, k].sum() == curves[:, k].sum()
            else f"specimens {', '.join(map(repr, who[:_MAX_LISTED]))}"
            + (f" (and {len(who) - _MAX_LISTED} more)" if len(who) > _MAX_LISTED else "")
        )
        cases.append(f"{LOAD_CASES[k]} ({names})")
    nmm = moments[(measured & big[:, :, None]).any(axis=(0, 1))]
    rest = moments[(measured & ~big[:, :, None]).any(axis=(0, 1))]
    raise InputDataError(
        f"{meas.source}: the moments of load case {'; '.join(cases)} look like N·mm, not Nm: "
        f"field moment_nm holds {_fmt(nmm)} there, and {_fmt(rest)} for the other curves. "
        "femcal reads moments in Nm, and would drop those points as beyond the moments the "
        "surrogate is used at. Divide those moments by 1000 (e.g. 2500 N·mm = 2.5 Nm) and run "
        "again."
    )
