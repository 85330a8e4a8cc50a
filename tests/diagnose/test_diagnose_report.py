"""The diagnosis' summary text (femcal.diagnose.report)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from femcal.diagnose.explain import _repeats_grid
from femcal.diagnose.report import PRACTICAL_REPEATS, _next
from femcal.diagnose.result import SpecimenDiagnosis


def _repeats(
    needed: float, difference_deg: float, noise_deg: float, shared_var: float = 0.0
) -> int | None:
    """:func:`_repeats_grid` at one point, ``None`` where no number of repeats settles it."""
    k = float(_repeats_grid(needed, np.array(difference_deg), np.array(noise_deg), shared_var))
    return None if not math.isfinite(k) else int(k)


def _specimen(next_measurement):
    return SpecimenDiagnosis(
        specimen="S1",
        verdict="facet_contact",
        baseline_mae_deg=0.2,
        ranking=[],
        residuals=np.zeros((4, 3)),
        next_measurement=next_measurement,
    )


def _point(sigma_apart: float, gap: float = 4.0, **extra):
    return {
        "load_case": "Extension",
        "moment_nm": 7.5,
        "difference_deg": -0.1,
        "difference_sigma": sigma_apart,
        "repeats_to_settle": _repeats(10.0 + gap, sigma_apart * 0.05, 0.05),
        **extra,
    }


@pytest.mark.parametrize(
    ("apart", "expected"), [(3.0, 2), (14**0.5, 1), (1.0, 14), (0.1, 1400), (0.0, None)]
)
def test_repeats_settle_the_criterion_gap_whichever_model_is_right(apart, expected):
    # min_delta 10 + gap 4 = 14 to gain; each measurement adds apart^2 on average.
    assert _repeats(14.0, apart * 0.05, 0.05) == expected


@pytest.mark.parametrize(
    ("shared_sd", "expected"),
    [(0.0, 2), (0.02, 3), (0.03, 4), (0.039, 30), (0.15 / 14**0.5, None), (0.05, None)],
)
def test_repeats_do_not_average_the_error_they_share(shared_sd, expected):
    """The mean of k repeats at one point has variance noise^2 / k + shared (the surrogate's
    error there, the models' own uncertainty): k = noise^2 / (difference^2 / needed - shared)
    (a 0.15 deg difference, 3 noise sd, needed 14: 1.6, 2.1, 3.5 and 29.0 repeats, rounded
    up), and none settle it once the shared part alone reaches difference^2 / needed."""
    assert _repeats(14.0, 0.15, 0.05, shared_sd**2) == expected


def test_a_practical_point_says_how_many_measurements_settle_it():
    n = {"between": ["facet_contact", "facet_contact+neutral_zone"], **_point(3.0)}
    text = _next(_specimen(n))
    assert text == (
        "facet_contact vs facet_contact+neutral_zone: Extension at 7.5 Nm "
        "(-0.100°, 3.0σ, 2 measurements)"
    )


def test_a_point_beyond_the_protocol_names_the_practical_one_within_it_or_says_there_is_none():
    inner_ok = _point(2.0, moment_nm=5.0)
    n = {
        "between": ["a", "b"],
        **_point(3.0),
        "within_measured_range": False,
        "within_protocol": inner_ok,
    }
    text = _next(_specimen(n))
    assert "beyond the protocol); within the protocol: Extension at 5 Nm" in text
    assert text.endswith("4 measurements)")
    n["within_protocol"] = _point(0.5, moment_nm=5.0)
    assert _next(_specimen(n)).endswith("none practical within the protocol (at most 0.5σ)")


def test_models_that_barely_differ_get_no_measurement_to_make():
    assert _repeats(14.0, 0.5 * 0.05, 0.05) > PRACTICAL_REPEATS
    text = _next(_specimen({"between": ["none", "facet_contact"], **_point(0.1)}))
    assert text == (
        "none vs facet_contact: no practical measurement tells them apart "
        "(at most 0.1σ, Extension at 7.5 Nm)"
    )
    assert _next(_specimen(None)) == ""


def _diagnosis(next_measurement):
    from femcal.diagnose.result import Diagnosis

    moments = np.array([1.0, 2.5, 5.0])
    s = _specimen(next_measurement)
    s.residuals = np.full((4, 3), 0.01)
    return Diagnosis(
        specimens=[s],
        sigma_deg=0.05,
        noise_deg=0.05,
        noise_sd_deg=0.0,
        surrogate_error_deg=0.0,
        moments=moments,
        seconds=0.0,
    )


def _marks(tmp_path, monkeypatch, next_measurement) -> tuple[list, list[str]]:
    """The dotted 'measure next' lines of a specimen's figure as (panel title, x), and the
    figure's notes."""
    from matplotlib.figure import Figure

    from femcal.diagnose.report import plot_specimen

    seen = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: seen.append(fig))
    plot_specimen(_diagnosis(next_measurement), 0, np.ones((4, 3)), tmp_path / "S1.png")
    (fig,) = seen
    lines = [
        (ax.get_title(), float(line.get_xdata()[0]))
        for ax in fig.axes
        for line in ax.get_lines()
        if line.get_linestyle() == ":"
    ]
    # the notes wrap to the figure's width: compared as one line
    return lines, [
        " ".join(t.get_text().split()) for t in fig.texts if "Measure next" in t.get_text()
    ]


def test_the_figure_marks_a_practical_measurement_and_only_that(tmp_path, monkeypatch):
    n = {"between": ["facet_contact", "facet_contact+neutral_zone"], **_point(3.0)}
    lines, notes = _marks(tmp_path, monkeypatch, n)
    assert lines == [("extension", 7.5)]
    assert notes == [
        "Measure next to tell facet_contact from facet_contact+neutral_zone: extension at "
        "7.5 Nm (-0.100°, 3.0σ, 2 measurements)."
    ]
    # beyond the protocol, and within it practical too: both marked
    inner = _point(2.0, moment_nm=4.0)
    n = {**n, "within_measured_range": False, "within_protocol": inner}
    lines, notes = _marks(tmp_path, monkeypatch, n)
    assert lines == [("extension", 7.5), ("extension", 4.0)]
    assert notes[0].endswith(
        "(-0.100°, 3.0σ, 2 measurements), beyond the protocol; within the protocol: extension "
        "at 4 Nm (-0.100°, 2.0σ, 4 measurements)."
    )
    # within the protocol not practical: only the point beyond it
    n["within_protocol"] = _point(0.5, moment_nm=4.0)
    assert _marks(tmp_path, monkeypatch, n)[0] == [("extension", 7.5)]
    # nothing practical: nothing marked, nothing said
    assert _marks(tmp_path, monkeypatch, {**n, **_point(0.5)}) == ([], [])


def test_the_point_within_the_protocol_never_settles_sooner():
    """It is the best point of a subset of the moments searched: at most as far apart."""
    from femcal.diagnose.report import practical_next

    n = {"between": ["a", "b"], **_point(0.5), "within_protocol": _point(0.5, moment_nm=4.0)}
    assert practical_next(_specimen(n)) is None
    assert practical_next(_specimen({**n, **_point(3.0)}))["moment_nm"] == 7.5


def test_the_notes_below_a_figure_lie_inside_it_below_the_axes(tmp_path):
    """No tight box crops the saved figure: the notes' band must hold every line, between
    the figure's bottom edge and the axes' tick labels."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from femcal.diagnose.report import _place_notes

    fig = Figure(figsize=(15.0, 6.6))
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 4, sharex=True)
    for ax in axes[1]:
        ax.set_xlabel("moment (Nm)")
    notes = ["Flexion: " + "less rotation than the model " * 12, "Extension: short"]
    _place_notes(fig, notes)
    renderer = fig.canvas.get_renderer()
    (text,) = fig.texts
    box = text.get_window_extent(renderer)
    frame = fig.bbox
    assert text.get_text().count("\n") == 2  # the long note wrapped once
    assert frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0
    labels = max(ax.get_tightbbox(renderer).y0 for ax in axes[1])
    assert box.y1 < labels


def test_a_figure_drawn_again_for_another_specimen_matches_a_new_one(tmp_path, monkeypatch):
    """Each process draws every specimen on one figure: the PNG of a specimen drawn after
    another (with its curves, marks and notes) is pixel for pixel the one a new figure gives."""
    import matplotlib.image

    from femcal.diagnose import report

    noted = _diagnosis({"between": ["facet_contact", "facet_contact+neutral_zone"], **_point(3.0)})
    plain = _diagnosis(None)
    dense = np.geomspace(1.0, 5.0, 20)
    plain.specimens[0].curves = {"moments": dense, "none": np.outer(np.arange(1, 5), dense)}
    plain.specimens[0].verdict, plain.specimens[0].effects = "none", []
    rom = np.arange(12.0).reshape(4, 3)

    def png(diag, measured, name, new: bool):
        if new:
            monkeypatch.setattr(report, "_FIGURE", None)
        report.plot_specimen(diag, 0, measured, tmp_path / name)
        return matplotlib.image.imread(tmp_path / name)

    first = png(noted, np.ones((4, 3)), "noted-new.png", new=True)
    other = png(plain, rom, "plain-new.png", new=True)
    assert first.shape != other.shape  # the notes' band makes the figure taller
    png(noted, np.ones((4, 3)), "noted-first.png", new=True)
    assert np.array_equal(png(plain, rom, "plain-after.png", new=False), other)
    assert np.array_equal(png(noted, np.ones((4, 3)), "noted-after.png", new=False), first)


def test_the_summary_says_where_each_effect_of_the_verdict_acts():
    from femcal.diagnose.report import _probable

    s = SpecimenDiagnosis(
        specimen="S",
        verdict="facet_contact",
        baseline_mae_deg=0.1,
        ranking=[],
        residuals=np.zeros((4, 3)),
        effects=["facet_contact"],
        model=["facet_contact@Extension,LateralBending,AxialRotation"],
        load_cases={"facet_contact": ["Extension", "LateralBending", "AxialRotation"]},
        probabilities={
            "models": {"facet_contact@Extension,LateralBending,AxialRotation": 0.8},
            "inclusion": {"facet_contact": 1.0},
            "acts_in": {
                "facet_contact": {"Extension": 1.0, "LateralBending": 0.8, "AxialRotation": 1.0}
            },
        },
    )
    assert _probable(s).endswith(
        "; facet_contact acts in Extension, LateralBending 0.80, AxialRotation"
    )
    assert s.to_dict()["load_cases"] == s.load_cases


def test_specimens_whose_names_reduce_to_one_file_name_get_a_figure_each(tmp_path, monkeypatch):
    """Named over the whole cohort, whichever process draws them: by the workers' groups
    (draw_group, one specimen each) or by write_diagnosis."""
    from femcal.diagnose import report
    from femcal.diagnose.result import Diagnosis

    monkeypatch.setattr(report, "free_cores", lambda: 1)  # drawn in this process
    one, other = _diagnosis(None), _diagnosis(None)
    one.specimens[0].specimen, other.specimens[0].specimen = "a b", "a_b"
    cohort = Diagnosis(
        specimens=[one.specimens[0], other.specimens[0]],
        sigma_deg=0.05,
        noise_deg=0.05,
        noise_sd_deg=0.0,
        surrogate_error_deg=0.0,
        moments=one.moments,
        seconds=0.0,
    )
    rom = np.ones((2, 4, 3))
    pdir = tmp_path / "groups"
    pdir.mkdir()
    paths = report.figure_paths(["a b", "a_b"], pdir)
    for group, rows in ((one, [0]), (other, [1])):
        report.draw_group(group, np.array(rows), rom, paths, None)
    assert sorted(p.name for p in pdir.iterdir()) == ["a_b.png", "a_b_.png"]
    assert report.drawn_figures(cohort, pdir) == {0, 1}
    report.write_diagnosis(cohort, rom, tmp_path / "out")
    assert sorted(p.name for p in (tmp_path / "out" / "plots").iterdir()) == [
        "a_b.png",
        "a_b_.png",
    ]
