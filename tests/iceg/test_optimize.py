"""``iceg optimize``: a wrong closure shows in loop_closures.csv and removing it restores the
clean trajectory; a closure without pose is matched by ICE."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from frontends.carmen import write_carmen
from frontends.simulate import office_world, simulate
from iceg import session
from iceg.cli import app
from iceg.evaluation import position_errors
from iceg_common import se2

runner = CliRunner()
N_SCANS = 260


@pytest.fixture(scope="module")
def office(tmp_path_factory):  # type: ignore[no-untyped-def]
    folder = tmp_path_factory.mktemp("optimize")
    run = simulate(office_world(), seed=1)
    write_carmen(folder / "office.clf", run.scans[:N_SCANS])
    result = runner.invoke(app, ["run", str(folder / "office.clf"), "--out", str(folder / "run")])
    assert result.exit_code == 0, result.output
    return folder, run.true_poses[:N_SCANS]


def _error_m(folder: Path, truth: np.ndarray) -> float:
    return position_errors(session.read(folder).trajectory()[1], truth).mean_m


def test_removing_an_injected_wrong_closure_restores_the_clean_run(office) -> None:  # type: ignore[no-untyped-def]
    folder, truth = office
    clean = _error_m(folder / "run", truth)
    bad = runner.invoke(
        app,
        [
            "optimize",
            str(folder / "run"),
            "--add-closure",
            "10 80 1.0 0.5 10",
            "--out",
            str(folder / "bad"),
        ],
    )
    assert bad.exit_code == 0, bad.output
    assert _error_m(folder / "bad", truth) > 10 * clean
    rows = session.read_closures_csv(folder / "bad" / "loop_closures.csv")
    accepted = [r for r in rows if r["status"] == "accepted"]
    worst = max(accepted, key=lambda r: float(r["chi2"]))  # the user finds the wrong one
    assert (worst["node_i"], worst["node_j"], worst["why"]) == ("10", "80", "added by the user")
    assert float(worst["chi2"]) > 100.0
    fixed = runner.invoke(
        app,
        [
            "optimize",
            str(folder / "bad"),
            "--remove-factor",
            worst["factor"],
            "--out",
            str(folder / "fixed"),
        ],
    )
    assert fixed.exit_code == 0, fixed.output
    assert _error_m(folder / "fixed", truth) == pytest.approx(clean, rel=1e-3)
    a = session.read(folder / "run").trajectory()[1]
    b = session.read(folder / "fixed").trajectory()[1]
    assert np.abs(a - b).max() < 1e-5


def test_closure_without_pose_is_matched_by_ice(office) -> None:  # type: ignore[no-untyped-def]
    folder, truth = office
    result = runner.invoke(
        app,
        ["optimize", str(folder / "run"), "--add-closure", "10 14", "--out", str(folder / "ice")],
    )
    assert result.exit_code == 0, result.output
    s = session.read(folder / "ice")
    assert s.edited
    (row,) = [
        r
        for r in session.read_closures_csv(folder / "ice" / "loop_closures.csv")
        if r["why"] == "added by the user"
    ]
    truth_ij = truth[s.arrays["n_scan"][[10, 14]]]
    expected = np.array([float(row[k]) for k in ("x_m", "y_m", "theta_rad")])
    assert np.abs(se2.between(truth_ij[0], truth_ij[1])[:2] - expected[:2]).max() < 0.03
    assert float(row["correlation"]) > 0.5
    # an edited session loads and continues
    slam = session.load(folder / "ice")
    assert slam.graph.n_factors == s.arrays["g_kind"].shape[0]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--remove-factor", "0"], "prior"),
        (["--remove-factor", "99999"], "factors 0.."),
        (["--add-closure", "1 2 3"], "NODE_I NODE_J"),
        (["--add-closure", "1 99999"], "two different nodes"),
    ],
)
def test_bad_edits_fail_with_one_line(office, args, message) -> None:  # type: ignore[no-untyped-def]
    folder, _ = office
    result = runner.invoke(app, ["optimize", str(folder / "run"), *args])
    assert result.exit_code == 1
    assert message in result.output
