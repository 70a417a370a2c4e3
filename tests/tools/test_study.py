"""``ar-anchor study``: quick runs of the three studies, their files, the physics they must show, bad options."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ar_anchor.errors import InputError
from ar_anchor.tools.study import STUDIES, PnPSetup, make_correspondences, run_study, solve_trial
from tests.helpers import study_args

RERUN = Path(sys.executable).with_name("rerun")


parse = study_args


@pytest.fixture(scope="module")
def quick_out(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """All three studies in quick mode, written once for the whole module."""
    out = tmp_path_factory.mktemp("study")
    assert run_study(parse(["all", "--quick", "--out", str(out)])) == 0
    return out


def load(out: Path, name: str) -> dict:
    return json.loads((out / f"{name}.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("name", STUDIES)
def test_each_study_writes_figure_table_json_and_recording(quick_out, name):
    # then
    for suffix in ("png", "md", "json", "rrd"):
        path = quick_out / f"{name}.{suffix}"
        assert path.is_file() and path.stat().st_size > 0, path
    assert (quick_out / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    result = load(quick_out, name)
    assert result["study"] == name
    assert "--quick" in result["meta"]["command"]
    assert f"({name}.png)" in (quick_out / f"{name}.md").read_text()
    assert not list(quick_out.glob(".*tmp")), "a partial recording was left behind"


@pytest.mark.parametrize("name", STUDIES)
def test_recording_is_a_valid_rrd_with_the_study_plots(quick_out, name):
    if not RERUN.exists():
        pytest.skip(f"{RERUN} not found")
    rrd = str(quick_out / f"{name}.rrd")
    verify = subprocess.run([str(RERUN), "rrd", "verify", rrd], capture_output=True, text=True, timeout=60)
    assert verify.returncode == 0, verify.stdout + verify.stderr
    printed = subprocess.run([str(RERUN), "rrd", "print", rrd], capture_output=True, text=True, timeout=60).stdout
    for entity in (f"{name}/figure", f"{name}/table", "Scalars"):
        assert entity in printed, entity


def test_outliers_ransac_recovers_millimetres_where_least_squares_is_metres_off(quick_out):
    summary = load(quick_out, "outliers")["summary"]
    assert summary["ransac_error_m"]["median"] < 0.01
    assert summary["plain_error_m"]["median"] > 0.5
    assert summary["ransac_error_m"]["p90"] < summary["plain_error_m"]["p10"]
    assert summary["honest_inliers"]["median"] >= summary["honest_points"] - 1
    assert summary["replaced_admitted_max"] <= 1


def test_ransac_threshold_below_the_noise_loses_recall_without_outliers(quick_out):
    result = load(quick_out, "ransac")
    cells = {(c["threshold_px"], c["contamination_pct"]): c for c in result["cells"]}
    # a 0.5 px threshold keeps at most about 1 - exp(-0.5) = 39 % of points with 0.5 px noise
    assert cells[0.5, 0.0]["median_recall"] < 0.6 < cells[2.0, 0.0]["median_recall"]
    for contamination in (0.0, 20.0, 40.0):
        assert cells[2.0, contamination]["success_pct"] == 100.0
        assert cells[2.0, contamination]["median_error_m"] < 0.01
    assert result["summary"]["thresholds"]["0.5"]["succeeds_up_to_pct"] is None


def test_jitter_board_below_marker_and_tracker_below_raw(quick_out):
    result = load(quick_out, "jitter")
    rows = result["distances"]
    assert [r["distance_m"] for r in rows] == [0.3, 1.0, 3.0]
    for row in rows:
        assert row["marker_raw"]["detected_pct"] == 100.0
        assert row["board_raw"]["rotation_std_deg"] < row["marker_raw"]["rotation_std_deg"]
        assert row["board_raw"]["distance_std_mm"] < row["marker_raw"]["distance_std_mm"]
    far = rows[-1]
    assert far["marker_tracker"]["rotation_std_deg"] * 5 < far["marker_raw"]["rotation_std_deg"]
    assert rows[0]["marker_raw"]["rotation_std_deg"] < far["marker_raw"]["rotation_std_deg"]
    assert "views" not in result


def test_one_seed_contaminates_a_superset_of_the_same_points_as_contamination_grows():
    # given
    setup = PnPSetup(points=40)
    # when
    low, high = make_correspondences(setup, 0.1, seed=3), make_correspondences(setup, 0.3, seed=3)
    # then
    np.testing.assert_array_equal(low.points_in_world, high.points_in_world)
    assert np.all(high.honest <= low.honest)
    assert (~low.honest).sum() == 4 and (~high.honest).sum() == 12
    np.testing.assert_array_equal(low.pixels[high.honest], high.pixels[high.honest])


def test_honest_points_are_in_view_at_their_depth_and_within_the_noise_of_the_truth():
    # given
    setup = PnPSetup()
    problem = make_correspondences(setup, 0.0, seed=0)
    # when
    in_camera = setup.camera_from_world.apply(problem.points_in_world)
    projected = setup.camera.project(in_camera)
    # then
    assert np.all((in_camera[:, 2] >= 4.0) & (in_camera[:, 2] <= 8.0))
    assert np.all((projected >= 0) & (projected <= np.array(setup.camera.size) - 1))
    residual = problem.pixels - projected
    assert 0.4 < residual.std() < 0.6
    # and with no outliers RANSAC at 2 px keeps (nearly) every point
    trial = solve_trial(setup, problem, 2.0)
    assert trial.recall > 0.95 and trial.ransac_error_m < 0.01 and trial.plain_error_m < 0.01


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["outliers", "--seeds", "0"], r"--seeds: must be in \[1, 100000\], got 0"),
        (["outliers", "--seed", "-1"], r"--seed: must be in \[0, 1e\+06\], got -1"),
        (["outliers", "--contamination", "100"], r"--contamination: percentages must be in \[0, 100\)"),
        (["ransac", "--contaminations", "0,97"], "leaves 4 honest points; 6 are needed"),
        (["ransac", "--thresholds", "1,two"], "--thresholds: expected numbers separated by commas"),
        (["ransac", "--thresholds", "0,2"], r"--thresholds: must all be in \[0.001, 1000\] px, got 0"),
        (["jitter", "--distances", "0.5,-1"], "--distances: must all be > 0 m"),
        (["jitter", "--distances", "30cm,1x"], r"--distances: expected lengths such as 50mm, 5cm or 0.05m"),
        (["jitter", "--distances", "50cm,-1m"], "--distances: must all be > 0 m"),
        (["jitter", "--marker-m=-5cm"], r"--marker-m: must be in"),
        (["jitter", "--frames", "20"], r"--frames: must be in \[32, 100000\]"),
        (["jitter", "--tilt-deg", "85"], r"--tilt-deg: must be in \[0, 80\)"),
    ],
)
def test_bad_option_is_an_input_error_naming_it_and_writes_nothing(tmp_path, argv, message):
    # given
    out = tmp_path / "study"
    # when / then
    with pytest.raises(InputError, match=message):
        run_study(parse([*argv, "--out", str(out)]))
    assert not out.exists()


def test_out_that_is_a_file_is_an_input_error(tmp_path):
    # given
    out = tmp_path / "taken"
    out.write_text("")
    # when / then
    with pytest.raises(InputError, match="a file, not a directory"):
        run_study(parse(["outliers", "--quick", "--out", str(out)]))


def test_unknown_study_is_rejected_by_the_parser():
    with pytest.raises(SystemExit):
        parse(["jitters"])
