"""`semservo reproduce`: one command re-runs the paper's experiments and writes the report
beside the paper's numbers; a quick subset here, its numbers parsed back."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

pytestmark = pytest.mark.integration


def test_reproduce_writes_the_report_and_keeps_finished_experiments(tmp_path):
    out = tmp_path / "reproduction"
    command = [sys.executable, "-m", "semservo", "reproduce", "--quick", "--only", "fig4", "table2", "--out", str(out)]
    done = subprocess.run(command, capture_output=True, text=True, timeout=110)
    assert done.returncode == 0, done.stdout + done.stderr
    report = (out / "README.md").read_text()
    assert "Table II" in report and "Fig. 4" in report
    # The table parsed back: four reference speeds, each with our error beside the paper's.
    rows = re.findall(r"^\| ([\d.]+) \| ([\d.]+), ([\d.]+) \| (\d)/(\d) \| ([\d.]+), ([\d.]+) \|$", report, re.M)
    assert [float(row[0]) for row in rows] == [4.3, 5.8, 8.6, 11.5]
    assert all(float(row[1]) < 1.0 and float(row[2]) < 1.0 and row[3] == row[4] for row in rows), rows
    assert (out / "fig4_cost_map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    fig4 = json.loads((out / "results" / "fig4.json").read_text())
    centre = len(fig4["offsets_px"]) // 2
    assert fig4["fourier"][centre][centre] < 1.0 < fig4["fourier"][0][0], "the cost is least at the desired pose"
    # Run again: finished experiments are kept, not redone.
    again = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert again.returncode == 0 and "kept from an earlier run" in again.stdout


def test_reproduce_refuses_an_unknown_experiment(tmp_path):
    done = subprocess.run([sys.executable, "-m", "semservo", "reproduce", "--only", "table9", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "table9" in done.stderr


def test_reproduce_table_one_from_the_library_alone(tmp_path):
    """Table I comes from the installed library (``semservo.reproduce.tilts``), not from
    the repository's bench folder: run from elsewhere, its three poses parsed back."""
    out = tmp_path / "reproduction"
    done = subprocess.run([sys.executable, "-m", "semservo", "reproduce", "--quick", "--only", "table1",
                           "--out", str(out)], capture_output=True, text=True, timeout=110, cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    report = (out / "README.md").read_text()
    number = r"([+-]?[\d.]+)"
    rows = re.findall(rf"^\| {number}, {number}, {number} \| {number}, {number}, {number} \| {number}, {number}, "
                      rf"{number} \|$", report, re.M)
    assert [tuple(float(value) for value in row[:3]) for row in rows] == [(15, -15, 70), (8, -8, 30), (3, 3, -5)]
    for row in rows:
        true, measured, error = (tuple(float(value) for value in row[start:start + 3]) for start in (0, 3, 6))
        assert all(abs(m - t - e) < 2e-3 for t, m, e in zip(true, measured, error)), row
        assert max(abs(e) for e in error[:2]) < 0.3 and abs(error[2]) < 0.05, row  # the paper's reach 0.82
        assert all(m * t > 0 for t, m in zip(true, measured)), "no sign flip (the paper had one at 3 degrees)"


def test_the_real_texture_tilt_bench_runs_on_a_picture_of_your_own(tmp_path):
    """``./dev bench tilt_real --image-files FILE`` (the README's line): the picture is
    the sample, its row says "yours", the paper's three poses are measured on a dense
    texture, and the results are written; a picture that cannot be read is a usage error that
    names it."""
    from pathlib import Path

    import cv2
    import numpy as np

    rng = np.random.default_rng(3)
    picture = tmp_path / "wafer.png"
    grains = cv2.GaussianBlur(rng.normal(size=(512, 512)), (0, 0), 1.5)
    cv2.imwrite(str(picture), np.clip(128 + 400 * grains, 0, 255).astype(np.uint8))
    bench = Path(__file__).parents[2] / "bench" / "tilt_real.py"
    out = tmp_path / "tilt_real.json"
    done = subprocess.run([sys.executable, str(bench), "--image-files", str(picture), "--models", "gaussian",
                           "--poses", "0", "--dof-poses", "0", "--out", str(out)],
                          capture_output=True, text=True, timeout=110)
    assert done.returncode == 0, done.stdout + done.stderr
    assert re.search(r"^\| wafer \| yours \| \d+ of 3 \|", done.stdout, re.M), done.stdout
    saved = json.loads(out.read_text())
    assert saved["yours"] == {"wafer": str(picture)}
    rows = saved["table_one"]["gaussian"]["wafer"]["table"]["rows"]
    # A fine, dense texture: every pose measured, within the worst-pose bound.
    assert len(rows) == 3 and not any(row["refused"] for row in rows), rows
    assert all(abs(error) < 0.3 for row in rows for error in row["plane"]), rows
    missing = subprocess.run([sys.executable, str(bench), "--image-files", str(tmp_path / "none.tif")],
                             capture_output=True, text=True, timeout=60)
    assert missing.returncode == 2 and "cannot read" in missing.stderr and "none.tif" in missing.stderr


def test_the_tilt_sampling_bench_measures_the_pull_between_samples(tmp_path):
    """``./dev bench tilt_sampling`` on one image and model, the taught view's focus on a
    sample and midway between two: a row per focus measure, and there (the samples lie
    symmetric about every kernel's focus) the flat view reads 0 without noise, whatever
    the reading; the poses against it are measured, the floor claimed is positive, and
    the plot is written."""
    from pathlib import Path

    bench = Path(__file__).parents[2] / "bench" / "tilt_sampling.py"
    out = tmp_path / "tilt_sampling.json"
    done = subprocess.run([sys.executable, str(bench), "--images", "jeol_grid", "--models", "gaussian", "--phases", "2",
                           "--out", str(out)], capture_output=True, text=True, timeout=110)
    assert done.returncode == 0, done.stdout + done.stderr
    for measure in ("eq. 13", "gradient"):
        assert re.search(rf"^\| jeol_grid \| gaussian \| {re.escape(measure)} \| [\d.]+ \|", done.stdout, re.M), done.stdout
    saved = json.loads(out.read_text())
    assert saved["phases"] == 2 and len(saved["poses"]) == 7
    for reading in saved["results"]["gaussian"]["jeol_grid"].values():
        assert reading["taught"] < 2e-3, reading
        assert len(reading["against"]) == 7 and all(0 <= value < 1.0 for value in reading["against"]), reading
        assert all(floor > 0 for floor in reading["floor"]), reading
        assert reading["refused"] == [0] * 7, reading  # a dense texture: every reading accepted
    assert out.with_suffix(".png").stat().st_size > 10_000  # the plot


def test_the_tilt_bounds_bench_says_where_the_limit_lies(tmp_path):
    """``./dev bench tilt_bounds`` on one image and model: a row per view, the pixels'
    bound under each measure's, and semservo's claim by either measure no tighter than
    that measure's bound; and where each reading loses: nearly all the information in the
    kernels read (the grid is textured everywhere), and planes from them, by the
    information's own weights and by semservo's."""
    from pathlib import Path

    bench = Path(__file__).parents[2] / "bench" / "tilt_bounds.py"
    out = tmp_path / "tilt_bounds.json"
    done = subprocess.run([sys.executable, str(bench), "--images", "jeol_grid", "--models", "gaussian", "--draws", "2",
                           "--out", str(out)], capture_output=True, text=True, timeout=110)
    assert done.returncode == 0, done.stdout + done.stderr
    assert re.search(r"^\| jeol_grid \| gaussian \| [\d.]+, [\d.]+ \|", done.stdout, re.M), done.stdout
    row = json.loads(out.read_text())["results"]["gaussian"]["jeol_grid"]
    for measure, bound in (("normalized_variance", row["eq13"]), ("gradient", row["gradient"])):
        reading = row["semservo"][measure]
        assert all(pixels < each <= claimed for pixels, each, claimed in zip(row["pixels"], bound, reading["claimed"]))
        assert reading["refused"] == 0, row
        assert reading["information_read"] > 0.9 and 0.5 < reading["scatter_over_bound"] < 5, reading
        assert all(0 < rms < 5 * each for rms, each in zip(reading["rms_exact_weights"], bound)), reading
    assert row["draws"] == 2
    assert re.search(r"^\| jeol_grid \| gaussian \| gradient \| [\d.]+, [\d.]+ \| [\d.]+% \| [\d.]+ \([\d.]+\) \|",
                     done.stdout, re.M), done.stdout
    assert out.with_suffix(".png").stat().st_size > 10_000  # the chain of losses, plotted
