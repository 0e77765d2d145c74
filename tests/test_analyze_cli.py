"""`meniscope analyze` and `meniscope fit` as users run them: real recordings from `meniscope simulate`, the
shipped models, REPORT.json in the layout of shared/spec/cli.md, one-line errors for bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service.analysis.results import Report
from service.csvtable import read_columns
from service.validation.score import ejection_matches, summary
from service.validation.truth import read_truth, truth_centre
from tests.servicekit import meniscope

REPORT_KEYS = {"schema", "source", "method", "ejections", "windows"}
WINDOW_KEYS = {
    "index",
    "start_frame",
    "end_frame",
    "status",
    "reason",
    "modes",
    "offset_mm",
    "settling_time_s",
    "settled",
    "r2",
}
MODE_KEYS = {"frequency_hz", "decay_rate_per_s", "amplitude_mm", "phase_rad", "frequency_ci_hz", "decay_rate_ci_per_s"}


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four windows at 19,000 frames/s, lab noise: 760 frames."""
    out = tmp_path_factory.mktemp("rec") / "rec.cine"
    done = meniscope("simulate", "--out", out, "--windows", "4", "--seed", "11")
    assert done.returncode == 0, done.stderr
    return out


def check_layout(path: Path) -> dict:
    """REPORT.json as cli.md lays it out: its keys, plain finite numbers (json refuses NaN here)."""
    data = json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"{path} holds {c}"))
    assert REPORT_KEYS <= data.keys() and data["schema"] == "meniscope.report/1"
    for w in data["windows"]:
        assert WINDOW_KEYS <= w.keys()
        assert all(MODE_KEYS <= m.keys() for m in w["modes"])
    Report.load(path)
    return data


@pytest.mark.parametrize("method", ["network", "direct"])
def test_analyze_writes_the_report_the_table_and_the_plot(recording: Path, tmp_path: Path, method: str):
    out = tmp_path / "report.json"
    done = meniscope("analyze", recording, "--method", method, "--out", out, "--quiet")
    assert done.returncode == 0, done.stderr
    data = check_layout(out)
    truth = read_truth(recording)
    assert data["method"] == method and data["source"]["frames"] == 760 and data["source"]["fps"] == 19000
    assert ejection_matches(np.array(data["ejections"]), np.array(truth["ejections"])) == (4, 4, 4)
    table = read_columns(out.with_suffix(".frames.csv"), ("frame", "t_s", "d_mm", "p", "a_mm", "b_mm", "centre_mm"))
    assert table.shape == (760, 7) and np.array_equal(table[:, 0], np.arange(760))
    # the per-frame D(0, t) follows the truth (how closely is the inverse method's business: see the bench)
    assert np.corrcoef(table[:, 6], truth_centre(truth))[0, 1] > 0.5
    assert out.with_suffix(".png").stat().st_size > 10_000
    # poles from the frames' brightness by default: each window says where its modes' poles came from
    assert data["fit"]["poles"] == "frames" and {w["poles_from"] for w in data["windows"]} <= {"frames", "series"}
    assert all((w["poles_from"] is None) == (not w["modes"]) for w in data["windows"])


def test_analyze_takes_the_poles_from_the_frames_unless_told(recording: Path, tmp_path: Path):
    truth = {w["start_frame"]: w["truth"]["f1"] for w in read_truth(recording)["windows"]}
    errors = {}
    for poles, series in (("frames", "steady"), ("series", "steady"), ("frames", "window")):
        out = tmp_path / f"{poles}-{series}.json"
        # the steady series as the frames give it, and as the window model (the default) corrects it
        args = ("--poles", poles, "--series", series, "--out", out, "--quiet")
        assert meniscope("analyze", recording, *args).returncode == 0
        data = json.loads(out.read_text())
        assert data["fit"]["poles"] == poles
        errors[poles, series] = np.array(
            [
                abs(w["modes"][0]["frequency_hz"] / truth[w["start_frame"]] - 1)
                for w in data["windows"]
                if w["modes"] and w["start_frame"] in truth
            ]
        )
        assert {w["poles_from"] for w in data["windows"] if w["modes"]} <= {poles, "series"}
    # on this recording D(0, t) alone doubles a window's frequency (the network's |a| response); the frames do not.
    # (Where the steady series is noisy the halving of the brightness' pole may still misread a window: the window
    # model's series, the default, holds every one.)
    doubled = errors["series", "steady"] > 0.5
    assert doubled.any() and (errors["frames", "steady"][doubled] < 0.03).all()
    assert np.median(errors["frames", "steady"]) < np.median(errors["series", "steady"])
    assert errors["frames", "window"].max() < 0.03


def test_analyze_fits_the_brightness_as_a_polynomial_of_the_modes_unless_told(recording: Path, tmp_path: Path):
    """``--brightness products`` (the default) or ``modes``: stored in the report; both take the poles from the
    frames, and the polynomial's decay rates are the closer to the truth (median over the windows)."""
    truth = {w["start_frame"]: w["truth"]["g1"] for w in read_truth(recording)["windows"]}
    errors = {}
    for model in ("products", "modes"):
        out = tmp_path / f"{model}.json"
        assert meniscope("analyze", recording, "--brightness", model, "--out", out, "--quiet").returncode == 0
        data = json.loads(out.read_text())
        assert data["fit"]["brightness_model"] == model and data["fit"]["poles"] == "frames"
        errors[model] = [
            abs(w["modes"][0]["decay_rate_per_s"] / truth[w["start_frame"]] - 1)
            for w in data["windows"]
            if w["modes"] and w["start_frame"] in truth
        ]
    assert np.median(errors["products"]) < np.median(errors["modes"])


def test_analyze_at_a_known_rate_and_from_the_printers_file(recording: Path, tmp_path: Path):
    listed = tmp_path / "ejections.txt"
    listed.write_text("0\n190\n380\n570\n")
    for option in (("--ejection-hz", "100"), ("--ejections", listed)):
        out = tmp_path / "r.json"
        done = meniscope("analyze", recording, *option, "--out", out, "--quiet")
        assert done.returncode == 0, done.stderr
        assert json.loads(out.read_text())["ejections"] == [0, 190, 380, 570]


def test_fit_recovers_the_true_motion_of_every_window(recording: Path, tmp_path: Path):
    truth = read_truth(recording)
    series = tmp_path / "series.csv"
    values = truth_centre(truth)
    values[[300, 301, 650]] = np.nan  # missing samples: empty cells
    series.write_text("value\n" + "\n".join("" if np.isnan(v) else f"{v:.12g}" for v in values) + "\n")
    out = tmp_path / "fit.json"
    done = meniscope("fit", series, "--fps", "19000", "--ejection-hz", "100", "--out", out, "--quiet")
    assert done.returncode == 0, done.stderr
    data = check_layout(out)
    assert data["ejections"] == truth["ejections"] and data["fit"]["poles"] == "series"  # no frames to take them from
    for w, tw in zip(data["windows"], truth["windows"]):
        assert w["status"] == "ok" and w["modes"][0]["frequency_hz"] == pytest.approx(tw["truth"]["f1"], rel=1e-4)
        assert w["modes"][0]["decay_rate_per_s"] == pytest.approx(tw["truth"]["g1"], rel=1e-3)
        assert w["offset_mm"] == pytest.approx(tw["offset_mm"], abs=1e-7)
    whole = meniscope("fit", series, "--fps", "19000", "--out", tmp_path / "one.json", "--quiet")
    assert whole.returncode == 0 and len(json.loads((tmp_path / "one.json").read_text())["windows"]) == 1


@pytest.mark.parametrize(
    "verb_args, names",
    [
        (("analyze", "missing.cine"), "missing.cine"),
        (("fit", "missing.csv", "--fps", "19000"), "missing.csv"),
        (("fit", "SERIES", "--fps", "-3"), "--fps"),
        (("fit", "SERIES", "--fps", "19000", "--ejections", "nowhere.txt"), "nowhere.txt"),
        (("analyze", "REC", "--method", "nearest", "--database", "nodb"), "nodb"),
        (("analyze", "REC", "--models", "nomodels"), "nomodels"),
        (("analyze", "REC", "--refine", "--poles", "frames"), "--poles"),
    ],
)
def test_bad_input_is_one_line_naming_the_culprit(recording: Path, tmp_path: Path, verb_args, names):
    series = tmp_path / "s.csv"
    series.write_text("value\n1\n2\n3\n")
    args = [{"SERIES": series, "REC": recording}.get(a, a) for a in verb_args]
    out = tmp_path / "out.json"
    out.write_text("kept")
    done = meniscope(*args, "--out", out, "--quiet")
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and names in done.stderr
    assert out.read_text() == "kept"  # nothing already recorded is lost


def test_a_csv_without_the_column_is_refused(tmp_path: Path):
    series = tmp_path / "s.csv"
    series.write_text("displacement\n1\n")
    done = meniscope("fit", series, "--fps", "100", "--out", tmp_path / "f.json")
    assert done.returncode == 2 and "value" in done.stderr and "s.csv" in done.stderr


def test_bench_analysis_scores_every_method_against_the_truth(recording: Path, tmp_path: Path):
    """(``bench fit``, the window-fit suite, has its own test in test_fit_suite.py.)"""
    out, reports = tmp_path / "analysis.json", tmp_path / "reports"
    done = meniscope(
        "bench", "analysis", "--recordings", recording.parent, "--methods", "direct", "--out", out, "--reports", reports
    )
    assert done.returncode == 0, done.stderr
    figures = json.loads(out.read_text())["methods"]["direct"]["lab"]
    assert figures["recall"] == figures["precision"] == 1.0 and figures["frames_per_s"] > 0
    assert 0 <= figures["offset_mm_coverage"] <= 1  # the share of windows whose interval holds the truth
    assert 0 <= figures["settled_right"] <= 1  # the share of windows whose settled verdict is the truth's
    assert "| direct | lab |" in out.with_suffix(".md").read_text()
    # the windows behind the figures, kept as analyze writes them: scored again, they give the same figures
    kept = Report.load(reports / "direct" / f"{recording.stem}.json")
    again = summary(kept, read_truth(recording))
    assert again["offset_mm_median"] == pytest.approx(figures["offset_mm_median"])
    assert again["frequency_p90"] == pytest.approx(figures["frequency_p90"])


def test_bench_analysis_asked_for_no_rows_says_so_and_writes_nothing(recording: Path, tmp_path: Path):
    """Window rows are the network method's (with ``--refine``, its refinement from the window model's fit):
    ``--series window`` with the direct method alone measures nothing, refined or not, a one-line error rather than
    an empty table."""
    out = tmp_path / "analysis.json"
    for extra in (("--methods", "direct", "--refine"), ("--methods", "direct")):
        done = meniscope(
            "bench", "analysis", "--recordings", recording.parent, "--series", "window", *extra, "--out", out
        )
        assert done.returncode == 2
        assert done.stderr.count("\n") == 1 and "--series" in done.stderr and "gives no rows" in done.stderr
        assert not out.exists()


def test_bench_analysis_refuses_reports_that_are_a_file(recording: Path, tmp_path: Path):
    taken = tmp_path / "reports"
    taken.write_text("kept")
    out = tmp_path / "analysis.json"
    done = meniscope("bench", "analysis", "--recordings", recording.parent, "--out", out, "--reports", taken)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "not a folder" in done.stderr
    assert taken.read_text() == "kept" and not out.exists()
