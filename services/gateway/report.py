"""A run's report (``GET /runs/{id}/report.png``): error, cost and channel voltages per
iteration, the panels of the paper's Fig. 9."""

from __future__ import annotations

import io

import matplotlib

matplotlib.use("Agg")
from matplotlib.figure import Figure  # noqa: E402  (after the backend is chosen)


def report_png(run: dict) -> bytes:
    moved = [r for r in run.get("trajectory", []) if r.get("error") is not None]
    figure = Figure(figsize=(10, 3.2), dpi=100)
    error_axes, cost_axes, voltage_axes = figure.subplots(1, 3)
    iterations = [r["iteration"] for r in moved]
    if moved:
        dofs = run.get("settings", {}).get("dofs", ["x", "y"])
        planar = [dof for dof in dofs if dof in ("x", "y", "rotation")]
        for index, name in enumerate(planar):
            error_axes.plot(iterations, [r["error"][index] if index < len(r["error"]) else None for r in moved],
                            label=f"e_{name}")
        for dof, key in (("alpha", "alpha_deg"), ("beta", "beta_deg")):  # the tilts, at each sweep (degrees)
            values = [(r["iteration"], r[key]) for r in moved if dof in dofs and r.get(key) is not None]
            if values:
                error_axes.plot(*zip(*values), ".", label=f"{dof} (deg)")
        cost_axes.semilogy(iterations, [max(r["cost"], 1e-12) for r in moved], color="black")
        for axis in ("x", "y"):
            values = [(r["iteration"], r["voltages"][axis]) for r in moved if (r.get("voltages") or {}).get(axis) is not None]
            if values:
                voltage_axes.plot(*zip(*values), label=f"V_{axis}")
    error_axes.set(title="error (px, deg)", xlabel="iteration")
    cost_axes.set(title="cost e'e", xlabel="iteration")
    voltage_axes.set(title="voltages (V)", xlabel="iteration")
    for axes in (error_axes, voltage_axes):
        if axes.lines:
            axes.legend(fontsize=8)
    for axes in (error_axes, cost_axes, voltage_axes):
        axes.grid(alpha=0.3)
    outcome = run.get("outcome") or {}
    figure.suptitle(f"run {run['id']}: {run.get('state')} after {run.get('iterations')} iterations"
                    f"{' (' + outcome.get('reason', '') + ')' if outcome.get('reason') else ''}", fontsize=10)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()
