"""Where the disc model fails on a cohort, and which physical effect is missing.

The search (:func:`diagnose`, :mod:`.search`) fits the disc alone and with the registered
effects, selects per specimen by an honest criterion and asks whether the chosen model explains
the data within the noise; what it says of each specimen is a :class:`SpecimenDiagnosis`
(:mod:`.result`). The pieces:

* :mod:`.options`: :class:`DiagnoseOptions`, how the search searches and decides;
* :mod:`.state`: what its steps share; :mod:`.forward`, :mod:`.forms` (tied or split per
  load case), :mod:`.elimination` (open world): the steps;
* :mod:`.probabilities`: how probable each model, effect and unexplained residue is;
* :mod:`.outside`: a disc outside the parameter box told apart from a missing element;
* :mod:`.fits`: fitting a model to many specimens at once (starts, Gauss-Newton, chi-square);
* :mod:`.explain`: adequacy tests, rankings, what each effect adds, what to measure next;
* :mod:`.discrepancy`: the smooth model discrepancy (Kennedy & O'Hagan) and its description;
* :mod:`.report`: the files, plots and tables a diagnosis writes.

Measured figures: the docs' benchmark pages.
"""

from femcal.diagnose.options import DiagnoseOptions
from femcal.diagnose.result import (
    NONE,
    OUTSIDE_BOX,
    UNEXPLAINED,
    Diagnosis,
    SpecimenDiagnosis,
    model_label,
    verdict_label,
)
from femcal.diagnose.search import diagnose

__all__ = [
    "NONE",
    "OUTSIDE_BOX",
    "UNEXPLAINED",
    "DiagnoseOptions",
    "Diagnosis",
    "SpecimenDiagnosis",
    "diagnose",
    "model_label",
    "verdict_label",
]
