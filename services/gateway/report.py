"""A run's report (``GET /runs/{id}/report.png``): error, cost and channel voltages per
iteration, the panels of the paper's Fig. 9. Pixels and degrees never share an axis: a
run that servoes the rotation or the tilts gets its own panel of angles (degrees)."""

from __future__ import annotations

import io
import math
import textwrap
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from matplotlib.figure import Figure

ANGULAR = ("rotation", "alpha", "beta")
ANGLE_LABELS = {"rotation": "γ (rotation)", "alpha": "α (tilt about x)", "beta": "β (tilt about y)"}


def run_dofs(run: dict) -> list[str]:
    """The run's degrees of freedom, gamma named rotation (as the controller does)."""
    dofs = run.get("dofs") or (run.get("settings") or {}).get("dofs") or ["x", "y"]
    return list(dict.fromkeys("rotation" if dof == "gamma" else dof for dof in dofs))


def angle_series(moved: list[dict], dofs: list[str]) -> dict[str, tuple[list[int], list[float]]]:
    """Per angular DOF, (iterations, degrees): the rotation error from the error vector
    (radians there, eq. 34), each tilt at every iteration a focus sweep had measured it."""
    planar = [dof for dof in dofs if dof in ("x", "y", "rotation")]
    series = {}
    if "rotation" in dofs:
        index = planar.index("rotation")
        points = [(r["iteration"], math.degrees(r["error"][index])) for r in moved
                  if index < len(r["error"]) and r["error"][index] is not None]
        series["rotation"] = tuple(map(list, zip(*points))) if points else ([], [])
    for dof in ("alpha", "beta"):
        if dof in dofs:
            points = [(r["iteration"], r[f"{dof}_deg"]) for r in moved if r.get(f"{dof}_deg") is not None]
            series[dof] = tuple(map(list, zip(*points))) if points else ([], [])
    return series


def report_png(run: dict) -> bytes:
    buffer = io.BytesIO()
    report_figure(run).savefig(buffer, format="png")
    return buffer.getvalue()


def report_figure(run: dict) -> Figure:
    """The report's figure: error (px), angle errors (deg, when the run servoes an
    angle), cost and voltages, one panel each."""
    # Imported here, not at the top: matplotlib is a second of the gateway's start, and
    # most gateways never draw a report. A bare Figure needs no backend (it saves
    # through Agg by itself).
    from matplotlib.figure import Figure

    moved = [r for r in run.get("trajectory", []) if r.get("error") is not None and r.get("action", "moved") == "moved"]
    dofs = run_dofs(run)
    angular = [dof for dof in dofs if dof in ANGULAR]
    translations = [dof for dof in dofs if dof in ("x", "y")]
    panels = (["error"] if translations or not angular else []) + (["angles"] if angular else []) + ["cost", "voltages"]
    figure = Figure(figsize=(10 if len(panels) <= 3 else 13, 3.2), dpi=100)
    axes = dict(zip(panels, figure.subplots(1, len(panels))))
    iterations = [r["iteration"] for r in moved]
    planar = [dof for dof in dofs if dof in ("x", "y", "rotation")]
    if "error" in axes:
        for dof in translations:
            index = planar.index(dof)
            axes["error"].plot(iterations, [r["error"][index] if index < len(r["error"]) else None for r in moved],
                               label=f"e_{dof}")
        axes["error"].set(title="error (px)", xlabel="iteration", ylabel="px")
    if "angles" in axes:
        for dof, (steps, degrees) in angle_series(moved, dofs).items():
            # The tilts are measured once per focus sweep: steps, not a smooth line.
            style = {"drawstyle": "steps-post"} if dof in ("alpha", "beta") else {}
            axes["angles"].plot(steps, degrees, label=ANGLE_LABELS[dof], **style)
        axes["angles"].axhline(0.0, color="grey", linewidth=0.8)
        axes["angles"].set(title="angle errors (deg)", xlabel="iteration", ylabel="deg")
    costs = [(i, r["cost"]) for i, r in zip(iterations, moved) if r.get("cost") is not None and r["cost"] > 0]
    if costs:
        axes["cost"].semilogy(*zip(*costs), color="black")
    axes["cost"].set(title="cost e'e", xlabel="iteration")
    for axis in ("x", "y"):
        values = [(r["iteration"], r["voltages"][axis]) for r in moved
                  if (r.get("voltages") or {}).get(axis) is not None]
        if values:
            axes["voltages"].plot(*zip(*values), label=f"V_{axis}")
    axes["voltages"].set(title="voltages (V)", xlabel="iteration", ylabel="V")
    for name, subplot in axes.items():
        subplot.grid(alpha=0.3)
        labels = subplot.get_legend_handles_labels()[1]
        if name != "cost" and labels:
            # Below the panel, in one row: inside, it covered the start of a curve (the
            # tilts' steps begin far from 0, where a legend sits).
            subplot.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.3), ncol=len(labels),
                           frameon=False)
    outcome = run.get("outcome") or {}
    title = (f"run {run['id']}: {run.get('state')} after {run.get('iterations')} iterations"
             f"{' (' + outcome.get('reason', '') + ')' if outcome.get('reason') else ''}")
    # Wrapped to the figure's width: a reason in words is often longer than one line.
    figure.suptitle(textwrap.fill(title, width=120), fontsize=9)
    figure.tight_layout()
    return figure
