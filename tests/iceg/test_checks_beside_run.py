"""A log run whose checks go on in a forked process beside it (``iceg.pipeline``; the run
stopping where they arrive is ``test_aside.py``'s): in every case the run that starts after
them, bit for bit."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pytest

from frontends import LaserScan
from frontends.carmen import write_carmen
from frontends.simulate import office_world, simulate
from iceg.config import IcegConfig
from iceg.pipeline import run_log


@pytest.fixture(scope="module")
def office_scans() -> list[LaserScan]:
    return list(simulate(office_world(), seed=0).scans)[:400]


def _logs(scans: list[LaserScan], directory: Path) -> dict[str, Path]:
    """The office's first 400 scans as recorded, with their odometry held over scans 200-349
    (a stall: read without it there), and with it one pose throughout (read laser-only)."""
    held_pose = scans[199].odom_pose
    held = [
        dataclasses.replace(s, odom_pose=held_pose) if 200 <= k < 350 else s
        for k, s in enumerate(scans)
    ]
    still = [dataclasses.replace(s, odom_pose=np.zeros(3)) for s in scans]
    logs = {"as recorded": scans, "held": held, "still": still}
    for name, written in logs.items():
        write_carmen(directory / f"{name}.clf", written)
    return {name: directory / f"{name}.clf" for name in logs}


@pytest.mark.parametrize("name", ["as recorded", "held", "still"])
def test_the_run_beside_its_checks_is_the_run_after_them(
    office_scans: list[LaserScan], tmp_path: Path, name: str, caplog: pytest.LogCaptureFixture
) -> None:
    # With one process the run waits for the checks; with two it runs beside them and, where
    # they read the log otherwise, starts again: the same trajectory, bit for bit, and the
    # same reading recorded.
    path = _logs(office_scans, tmp_path)[name]
    one = run_log(path, IcegConfig.model_validate({"slam": {"workers": 1}}))
    with caplog.at_level(logging.INFO, logger="iceg.pipeline"):
        two = run_log(path, IcegConfig.model_validate({"slam": {"workers": 2}}))
    again = "the checks read the log otherwise; the run starts again"
    assert (again in caplog.text) == (name != "as recorded")
    assert one.poses.tobytes() == two.poses.tobytes()
    for key in (
        "odometry_stalls",
        "odometry_check",
        "robot_body",
        "wall_dropouts",
        "odometry_calibration",
    ):
        assert one.metrics[key] == two.metrics[key], key
    stalls = [(s["first"], s["stop"]) for s in two.metrics["odometry_stalls"]]
    assert stalls == ([(200, 350)] if name == "held" else [])
    (reading,) = two.slam.log_readings.values()
    assert (
        reading["reader_options"]
        == {
            "as recorded": {},
            "held": {
                "odometry_stalls_s": [
                    [s["start_s"], s["end_s"]] for s in two.metrics["odometry_stalls"]
                ]
            },
            "still": {"laser_only": True},
        }[name]
    )
    assert one.slam is not None and two.slam is not None
    assert one.slam.log_readings == two.slam.log_readings
