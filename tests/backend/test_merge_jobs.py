"""Merge jobs: which stored patches the merge takes as they are."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from backend import merge_jobs


@pytest.mark.parametrize(
    ("attrs", "open_loop"),
    [
        ({"row_readings": np.linspace(0, 1e-6, 8)}, False),  # a Y sensor placed every row
        ({"row_readings": np.zeros(0)}, True),  # a scan generator on open-loop piezos
        ({"row_readings": np.array([0.0, np.nan, 2e-8])}, True),  # a sensor that did not read
        ({"source": "scan.sxm"}, False),  # uploaded: nothing known of its scanner
    ],
)
def test_self_calibration_is_chosen_for_scans_without_a_position_sensor(
    attrs: dict[str, Any], open_loop: bool
) -> None:
    assert merge_jobs.scanned_open_loop(attrs) is open_loop
