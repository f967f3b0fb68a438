"""A run's report (GET /runs/{id}/report.png): pixels and degrees on separate axes."""

from __future__ import annotations

import io
import math

from PIL import Image

from services.gateway.report import report_figure, report_png


def a_run(dofs: list[str], iterations: int = 40) -> dict:
    """A run record as the gateway stores it: a move per iteration, the error vector in
    pixels (x, y) and radians (rotation), the tilts as the last focus sweep measured them."""
    planar = [dof for dof in dofs if dof in ("x", "y", "rotation")]
    trajectory = []
    for i in range(1, iterations + 1):
        decay = math.exp(-i / 8)
        values = {"x": 20 * decay, "y": -15 * decay, "rotation": math.radians(3 * decay)}
        record = {"iteration": i, "action": "moved", "error": [values[dof] for dof in planar],
                  "cost": sum(values[dof] ** 2 for dof in planar), "voltages": {"x": 40 - 5 * decay, "y": 30 + 5 * decay}}
        if i >= 10:  # the first sweep's measurement comes later, then once per sweep
            record["alpha_deg"] = 2.0 * math.exp(-(i // 10) * 10 / 8)
            record["beta_deg"] = -1.5 * math.exp(-(i // 10) * 10 / 8)
        trajectory.append(record)
        trajectory.append({"iteration": i, "action": "held: stale (scanned during the last move)"})
    return {"id": "r1", "state": "converged", "iterations": iterations, "dofs": dofs, "settings": {"dofs": dofs},
            "outcome": {"reason": "under tolerance"}, "trajectory": trajectory}


def panels(figure) -> dict:
    return {axes.get_title(): axes for axes in figure.axes}


def test_a_five_dof_report_plots_pixels_and_degrees_on_separate_axes():
    figure = report_figure(a_run(["x", "y", "rotation", "alpha", "beta"]))
    shown = panels(figure)
    assert list(shown) == ["error (px)", "angle errors (deg)", "cost e'e", "voltages (V)"]
    assert [line.get_label() for line in shown["error (px)"].get_lines()] == ["e_x", "e_y"]
    angles = {line.get_label(): line for line in shown["angle errors (deg)"].get_lines() if line.get_label()[0] != "_"}
    assert set(angles) == {"γ (rotation)", "α (tilt about x)", "β (tilt about y)"}
    # In degrees, readable at their own scale: the rotation starts near 3 degrees (its
    # error vector holds radians), the tilts near their measured values.
    gamma = angles["γ (rotation)"].get_ydata()
    assert 2.0 < gamma[0] < 3.0 and abs(gamma[-1]) < 0.1
    assert angles["α (tilt about x)"].get_xdata()[0] == 10
    low, high = shown["angle errors (deg)"].get_ylim()
    assert high - low < 5, "the angle axis spans degrees, not the pixels' tens"


def test_an_x_y_report_has_no_angle_panel_and_keeps_its_size():
    figure = report_figure(a_run(["x", "y"]))
    assert list(panels(figure)) == ["error (px)", "cost e'e", "voltages (V)"]
    assert Image.open(io.BytesIO(report_png(a_run(["x", "y"])))).size == (1000, 320)


def test_a_rotation_only_report_and_an_empty_run_still_draw():
    assert list(panels(report_figure(a_run(["rotation"])))) == ["angle errors (deg)", "cost e'e", "voltages (V)"]
    empty = {"id": "r0", "state": "failed", "iterations": 0, "settings": {"dofs": ["x", "y"]}, "trajectory": []}
    assert report_png(empty)[:8] == b"\x89PNG\r\n\x1a\n"
