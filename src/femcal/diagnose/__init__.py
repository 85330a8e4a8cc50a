"""Where the disc model fails on a cohort, and which physical effect is missing.

The search (:func:`diagnose`, :mod:`.search`) fits the disc alone and with the registered
effects, selects per specimen by an honest criterion and asks whether the chosen model explains
the data within the noise; what it says of each specimen is a :class:`SpecimenDiagnosis`
(:mod:`.result`). The pieces:

* :mod:`.fits`: fitting a model to many specimens at once (starts, Gauss-Newton, chi-square);
* :mod:`.explain`: adequacy tests, rankings, what each effect adds, what to measure next;
* :mod:`.discrepancy`: the smooth model discrepancy (Kennedy & O'Hagan) and its description;
* :mod:`.report`: the files, plots and tables a diagnosis writes.

Measured figures: ``reports/bench_diagnose.md``.
"""

from femcal.diagnose.result import (
    NONE,
    UNEXPLAINED,
    Diagnosis,
    SpecimenDiagnosis,
    model_label,
    verdict_label,
)
from femcal.diagnose.search import diagnose

__all__ = [
    "NONE",
    "UNEXPLAINED",
    "Diagnosis",
    "SpecimenDiagnosis",
    "diagnose",
    "model_label",
    "verdict_label",
]
