"""End to end on a cohort with hidden effects: calibrate -> diagnose -> add effect -> recalibrate.

The "FE model" of this synthetic world is a small fitted surrogate itself (its curves at 1..5 Nm
in 0.5 Nm steps play the FE curves the planted cohorts are built from), so the surrogate's own
error is zero and the test isolates the search: does it name the planted effect, leave
effect-free specimens alone, and does adding the named effects bring the error down to the noise?
"""

from __future__ import annotations

import numpy as np
import pytest

from femcal.calibration import SurrogateCurveModel, calibrate
from femcal.diagnose import diagnose
from femcal.effects.composite import EffectModel
from femcal.effects.planted import NONE, make_cohort
from femcal.surrogates.nn import NeuralSurrogate

from synth import study_space, tidy_table

NOISE = 0.02
CLASSES = (NONE, "facet_contact", "ligament_tension", "neutral_zone")


@pytest.fixture(scope="module")
def world():
    table = tidy_table(48, seed=3)
    surrogate = NeuralSurrogate(
        study_space(), hidden=(32, 32), max_epochs=40, patience=40, batch_size=16, seed=0
    ).fit(table, table["rom_deg"].to_numpy())
    fe_moments = np.arange(1.0, 5.01, 0.5)  # the measured grid: no interpolation error
    rng = np.random.default_rng(7)
    configs = study_space().sample_uniform(40, rng)
    fe_rom = SurrogateCurveModel(surrogate, fe_moments).predict(configs)
    cohort = make_cohort(
        fe_moments, fe_rom, classes=CLASSES, n_per_class=4, noise_deg=NOISE, rng=rng
    )
    return surrogate, cohort


def test_calibrate_diagnose_add_the_effect_and_the_error_falls(world):
    surrogate, cohort = world
    base = SurrogateCurveModel(surrogate, cohort.moments)
    planted = cohort.truth["effect"].to_numpy()
    opts = {"n_bank_uniform": 1024, "noise_deg": NOISE}
    # 1. Calibrate the disc alone.
    before = calibrate(base, cohort.rom_deg, method="pgd", options=opts, seed=0)
    # 2. Diagnose: the verdict per specimen.
    diag = diagnose(base, cohort.rom_deg, specimens=cohort.specimens, noise_deg=NOISE)
    verdicts = np.array([s.verdict for s in diag.specimens])
    visible = (planted != NONE) & (before.mae_deg > 2 * NOISE)
    assert visible.sum() >= 6, before.mae_deg  # the cohort must test something
    # The bars: >= 90 % right where the disc alone fails, <= 10 % false effects.
    assert np.mean(verdicts[visible] == planted[visible]) >= 0.9, list(zip(planted, verdicts))
    assert np.mean(verdicts[planted == NONE] != NONE) <= 0.1
    # 3. Add the effects the diagnosis found (as a user adds them to params.yaml) ...
    found = sorted({v for v in verdicts if v != NONE})
    assert found, verdicts
    after = calibrate(EffectModel(base, found), cohort.rom_deg, method="pgd", options=opts)
    assert np.all(after.exceedance == 0)
    # 4. ... and the error falls: planted specimens to within 1.5x of the effect-free ones, and
    # no specimen gets worse (1e-3 deg: float32 rounding of the surrogate).
    none_mae = after.mae_deg[planted == NONE].mean()
    assert after.mae_deg[planted != NONE].mean() <= 1.5 * max(none_mae, NOISE / 2)
    assert before.mae_deg[planted != NONE].mean() > 2 * after.mae_deg[planted != NONE].mean()
    assert np.all(after.mae_deg <= before.mae_deg + 1e-3)
    # The added effects' parameters stay inside their bounds and are named in the result.
    assert after.parameter_names[base.dim :] == tuple(
        n for e in EffectModel(base, found).effects for n in e.names()
    )
