"""`cwfs-ros demo` reports the science-field figure and the optical FWHM, with a rotated camera."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from test_cli import run_cli

pytestmark = pytest.mark.ros


def test_demo_records_field_figure_and_fwhm_with_the_rotator(tmp_path: Path) -> None:
    proc = run_cli("demo", "--out", tmp_path, "--visits", "2", "--photons", "2e5",
                   "--wavefront-error", "500", "--rotator-angle", "35", timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "camera rotator 35 deg" in proc.stdout and "over the field" in proc.stdout
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["rotator_angle_deg"] == 35.0
    field, fwhm = summary["true_field_error_nm"], summary["fwhm_arcsec"]
    assert len(field) == 2 and len(fwhm) == 2
    assert all(np.isfinite(field)) and field[0] > 100.0 and 0.0 < fwhm[0] < 3.0
    with (tmp_path / "visits.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [float(r["rotator_angle_deg"]) for r in rows] == [35.0, 35.0]
    assert [float(r["true_field_error_nm"]) for r in rows] == pytest.approx(field, abs=1e-2)
    assert "true field error" in (tmp_path / "report.html").read_text()


def test_demo_refuses_a_rotator_angle_out_of_range(tmp_path: Path) -> None:
    proc = run_cli("demo", "--out", tmp_path, "--rotator-angle", "300")
    assert proc.returncode == 2 and "--rotator-angle must be in [-270, 270]" in proc.stderr
