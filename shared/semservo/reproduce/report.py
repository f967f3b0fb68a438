"""The reproduction's report: ``README.md`` with every table beside the paper's numbers and
the conditions, and the figures as PNG, from the results kept in ``<out>/results``."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable

import numpy as np

from semservo.reproduce import (EXPERIMENTS, FIGURE_CASES, LAW_FRAMES, PAPER_TABLE1_POSES, PAPER_TABLE2,
                                PAPER_TABLE3, PAPER_TABLE4, load, methods)
from semservo.reproduce.tilts import plot_fig8

CASE_NUMBERS = {case: index for index, case in enumerate(FIGURE_CASES, 1)}


def _fmt(value, digits: int = 2) -> str:
    return "–" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def _paper_cell(entry) -> str:
    ms, successes = entry
    return "× (0/6)" if ms is None else f"{ms} ({successes}/6)"


def table4_cell(result: dict, case: str, method: str) -> tuple[float, int]:
    """One cell of Table IV: the method's mean computation per iteration (ms) in the case,
    and how many of its trials reached the target."""
    trials = result["rows"][case][method]
    return (float(np.mean([t["compute_ms"] for t in trials if t["compute_ms"] is not None])),
            sum(_at_target(t, result) for t in trials))


def table4_lines(result: dict) -> list[str]:
    lines = ["| case | " + " | ".join(methods.LABELS[m] for m in methods.METHODS)
             + " | paper: ours, flow, SURF, FAST |", "| --- |" + " --- |" * (len(methods.METHODS) + 1)]
    for case in result["cases"]:
        cells = []
        for method in methods.METHODS:
            ms, ok = table4_cell(result, case, method)
            cells.append(f"{ms:.1f} ms ({ok}/{len(result['rows'][case][method])})")
        paper = ", ".join(_paper_cell(entry) for entry in PAPER_TABLE4[case])
        lines.append(f"| {CASE_NUMBERS[case]} {case} | " + " | ".join(cells) + f" | {paper} |")
    return lines


def _span(values, spec: str) -> str:
    """``low-high`` of ``values`` in ``spec``, or the one value when they are all alike
    (one trial read "0-0 of 1 trials")."""
    low, high = format(min(values), spec), format(max(values), spec)
    return low if low == high else f"{low}-{high}"


def table4_summary(result: dict) -> str:
    """Where semservo loses and where it does not, read from the table (a sentence
    written once went stale when the table was re-run)."""
    cases = result["cases"]

    def compute_ms(method: str, case: str) -> float:
        return table4_cell(result, case, method)[0]

    def successes(method: str, case: str) -> int:
        return table4_cell(result, case, method)[1]

    def case_list(chosen: list[str]) -> str:
        numbers = [str(CASE_NUMBERS[case]) for case in chosen]
        return ("case " if len(numbers) == 1 else "cases ") + ", ".join(numbers)

    ours = {case: successes("semservo", case) for case in cases}
    sentences = []
    for method in methods.METHODS[1:]:
        label = methods.LABELS[method]
        ratios = [compute_ms(method, case) / compute_ms("semservo", case) for case in cases]
        counts = [successes(method, case) for case in cases]
        matched = [case for case, count in zip(cases, counts) if count >= ours[case]]
        if max(ratios) < 1:
            sentences.append(f"{label} computes less per iteration ({_span(ratios, '.2f')} x "
                             f"semservo's) but reaches the tolerance in {_span(counts, 'd')} of "
                             f"{result['trials']} trials per case"
                             + (f", as often as semservo in {case_list(matched)} only" if matched else ""))
        elif matched:
            sentences.append(f"{label} matches semservo's successes in {case_list(matched)} at "
                             f"{_span(ratios, '.1f')} x its computation")
    more = [f"{methods.LABELS[method]} in {case_list(better)}" for method in methods.METHODS[1:]
            if (better := [case for case in cases if successes(method, case) > ours[case]])]
    return ("Where semservo loses or ties (read from the table): " + "; ".join(sentences) + ". "
            + ("Converging more often than semservo: " + "; ".join(more) + "." if more
               else "No method converges more often."))


#: Why each baseline fails where it does, in one line (the loop's own reasons follow).
WHY = {
    "photometric": "its error is linearised through the image gradients, which reach a few pixels even on the "
                   "pyramid's coarsest level: far from the goal its cost has flat valleys (along the part's long "
                   "edges) where the step vanishes, and brightness changes are error too",
    "dis": "dense flow needs the same texture in both frames; noise, a mask or changing levels break it into "
           "many motions",
    "farneback": "as DIS: a polynomial expansion of noisy or textureless frames gives no single motion",
    "sift": "keypoints need texture that survives the noise; a binary mask or a frame at 180 ns/px has too little",
    "orb": "as SIFT, with binary descriptors that noise flips more easily",
    "semservo": "",
}


def _at_target(trial: dict, result: dict) -> bool:
    """Converged, and (where the result says so) truly at the target."""
    limit = result.get("at_target_px")
    return trial["outcome"] == "converged" and (limit is None or trial["true_error_px"] <= limit)


def _reason(trial: dict, result: dict) -> str:
    if trial["outcome"] == "converged":
        return f"stopped within tolerance by its own measure {trial['true_error_px']:.0f} px from the target (truth)"
    return trial["reason"]


def failures(result: dict) -> list[str]:
    """One line per method and case where it failed: the reason the loop gave."""
    lines = []
    for case in result["cases"]:
        for method in methods.METHODS:
            reasons = sorted({_reason(t, result) for t in result["rows"][case][method] if not _at_target(t, result)})
            if reasons:
                why = f" ({WHY[method]})" if WHY.get(method) else ""
                lines.append(f"- {methods.LABELS[method]}, case {CASE_NUMBERS[case]} ({case}): "
                             f"{'; '.join(reasons)}{why}")
    return lines


def table3_lines(result: dict) -> list[str]:
    lines = ["| case | true error x, y (um) | std x, y (um) | image-measured error (px) | RMSE | PSNR (dB) | "
             "converged | paper: accuracy x, y (um) | paper: std x, y | paper: RMSE, PSNR |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for case in FIGURE_CASES:
        trials = result["rows"].get(case, [])
        if not trials:
            continue
        errors = np.abs([t["true_error_um"] for t in trials])
        mean = errors.mean(axis=0)
        # One trial (--quick) has no spread to give: '–', not 0.0000.
        std = errors.std(axis=0) if len(trials) > 1 else (None, None)
        measured = [t["measured_error_px"] for t in trials if t["measured_error_px"] is not None]
        rmse = [t["rmse"] for t in trials if "rmse" in t]
        psnr = [t["psnr_db"] for t in trials if "psnr_db" in t]
        ok = sum(t["outcome"] == "converged" for t in trials)
        paper = PAPER_TABLE3.get(case, (None,) * 6)
        lines.append(
            f"| {CASE_NUMBERS[case]} {case} | {mean[0]:.3f}, {mean[1]:.3f} | {_fmt(std[0], 4)}, {_fmt(std[1], 4)} | "
            f"{_fmt(np.mean(measured) if measured else None, 3)} | {_fmt(np.mean(rmse) if rmse else None)} | "
            f"{_fmt(np.mean(psnr) if psnr else None)} | {ok}/{len(trials)} | {_fmt(paper[0])}, {_fmt(paper[1])} | "
            f"{_fmt(paper[2], 4)}, {_fmt(paper[3], 4)} | {_fmt(paper[4])}, {_fmt(paper[5])} |")
    return lines


def table2_lines(result: dict) -> list[str]:
    lines = ["| reference scan speed (us/px) | true error x, y (px) | converged | paper: error x, y (px) |",
             "| --- | --- | --- | --- |"]
    for dwell, paper in PAPER_TABLE2.items():
        trials = result["rows"].get(str(dwell), [])
        if not trials:
            continue
        errors = np.abs([np.array(t["true_error_um"]) / t["pixel_um"] for t in trials]).mean(axis=0)
        ok = sum(t["outcome"] == "converged" for t in trials)
        lines.append(f"| {dwell} | {errors[0]:.3f}, {errors[1]:.3f} | {ok}/{len(trials)} | {paper[0]}, {paper[1]} |")
    return lines


def table1_lines(result: dict) -> list[str]:
    lines = ["| true alpha, beta, gamma (deg) | measured alpha, beta, gamma (deg) | error (deg) |",
             "| --- | --- | --- |"]
    for row in result["rows"]:
        alpha, beta, gamma = row["pose"]
        errors = (row["plane"][0], row["plane"][1], row["gamma_compensated"])
        measured = (alpha + errors[0], beta + errors[1], gamma + errors[2])
        lines.append(f"| {alpha:g}, {beta:g}, {gamma:g} | {measured[0]:.3f}, {measured[1]:.3f}, {measured[2]:.3f} | "
                     f"{errors[0]:+.3f}, {errors[1]:+.3f}, {errors[2]:+.4f} |")
    return lines


def plot_fig4(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    offsets = np.array(result["offsets_px"])
    figure, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    for ax, key, title in ((axes[0], "fourier", "semservo: e'e of the measured shift (px^2)"),
                           (axes[1], "photometric", "photometric: mean (I - I*)^2")):
        values = np.array(result[key], dtype=float)
        image = ax.contourf(offsets, offsets, values, levels=20, cmap="viridis")
        figure.colorbar(image, ax=ax)
        ax.set(title=title, xlabel="x displacement (px)", ylabel="y displacement (px)")
    figure.suptitle("Cost around the desired pose (cf. paper Fig. 4)")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def plot_runs(case: str, trials: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    for index, trial in enumerate(trials[:3]):
        moved = [r for r in trial.get("records", []) if "error_px" in r]
        iterations = [r["iteration"] for r in moved]
        axes[0].plot(iterations, [r["error_px"] for r in moved], label=f"trial {index + 1}")
        axes[1].semilogy(iterations, [max(r.get("cost", r["error_px"] ** 2), 1e-6) for r in moved])
        volts = [(r["iteration"], r["voltages"]["x"], r["voltages"]["y"]) for r in moved if r.get("voltages")]
        if volts:
            steps, vx, vy = zip(*volts)
            axes[2].plot(steps, vx, color=f"C{index}")
            axes[2].plot(steps, vy, "--", color=f"C{index}")
    axes[0].set(title="error (px)", xlabel="iteration")
    axes[1].set(title="cost e'e (eq. 32)", xlabel="iteration")
    axes[2].set(title="voltages x (solid), y (dashed)", xlabel="iteration")
    axes[0].legend(fontsize=8)
    figure.suptitle(f"case {CASE_NUMBERS.get(case, '')} {case}: three trials (cf. paper Figs. 9-11)")
    figure.tight_layout()
    figure.savefig(path, dpi=90)
    plt.close(figure)


LAW_LABELS = {("position", "semservo"): "position law", ("paper", "semservo"): "paper's law",
              ("paper", "photometric"): "photometric DVS (paper's law)"}
MODEL_LABELS = {"calibrated": "calibrated", "uncalibrated": "no calibration (nominal stroke)",
                "other-stage+15%": "another stage's (+15 %)", "other-stage-15%": "another stage's (-15 %)"}


def _offset_label(offset) -> str:
    return offset if isinstance(offset, str) else f"{offset * 100:g} % of the field"


def _cells(rows: list[dict]) -> dict:
    """Fresh frames, frames scanned, seconds (medians; fresh frames' worst), true final
    error (median, worst), converged of N, over ``rows``."""
    if not rows:
        return {}
    fresh = [r["fresh_frames"] for r in rows]
    return {"fresh": float(np.median(fresh)), "fresh_max": int(max(fresh)),
            "scanned": float(np.median([r["frames_scanned"] for r in rows])),
            "seconds": float(np.median([r["seconds"] for r in rows])),
            "seconds_max": float(max(r["seconds"] for r in rows)),
            "error": float(np.median([r["true_error_px"] for r in rows])),
            "error_max": float(max(r["true_error_px"] for r in rows)),
            # Where the sample rested (the vibration left out); rows measured before it was kept lack it.
            "stage_error_max": (float(max(r["stage_error_px"] for r in rows))
                                if all("stage_error_px" in r for r in rows) else None),
            "overshoot_max": float(max(r.get("overshoot_px", 0.0) for r in rows)),
            "converged": sum(r["outcome"] == "converged" for r in rows), "n": len(rows)}


def _select(result: dict, **match) -> list[dict]:
    """The rows matching; a law's rows are those on its default frames
    (:data:`semservo.reproduce.LAW_FRAMES`) unless ``frames`` is given (rows measured
    before partial frames existed were on whole ones)."""
    if "law" in match and "frames" not in match:
        match["frames"] = LAW_FRAMES[match["law"]] if match.get("method", "semservo") == "semservo" else "whole"
    return [r for r in result["rows"] if all(r.get(key, "whole" if key == "frames" else None) == value
                                             for key, value in match.items())]


def _paper_at_best(result: dict, **match) -> tuple[dict, str]:
    """The paper's law's cells on whichever frames (whole or partial) bring it to the
    target sooner (median seconds), and which."""
    options = [(_cells(_select(result, law="paper", method="semservo", frames=frames, **match)), frames)
               for frames in ("whole", "partial")]
    options = [(cells, frames) for cells, frames in options if cells]
    return min(options, key=lambda option: option[0]["seconds"]) if options else ({}, "")


def _law_cell(cell: dict) -> str:
    if not cell:
        return "–"
    return (f"{cell['fresh']:g} ({cell['fresh_max']}) / {cell['scanned']:g} / {cell['seconds']:.1f} s / "
            f"{cell['error']:.3f} ({cell['error_max']:.3f}) px / {cell['converged']}/{cell['n']}")


def time_to_target_summary(result: dict) -> dict:
    """Per preset, the headline numbers and the targets of issue #28, calibrated model."""
    summary = {}
    for case in result["cases"]:
        position = _cells(_select(result, case=case, law="position", method="semservo", stage_model="calibrated"))
        paper, paper_frames = _paper_at_best(result, case=case, stage_model="calibrated")
        ratios = {}
        for model in result["models"]:
            if model == "calibrated":
                continue
            other = _cells(_select(result, case=case, law="position", method="semservo", stage_model=model))
            if other:
                ratios[model] = (other, other["fresh"] / position["fresh"])
        summary[case] = {"position": position, "paper": paper, "paper_frames": paper_frames,
                         "speedup": paper["seconds"] / position["seconds"] if position and paper else None,
                         "models": ratios,
                         "frames": {(law, frames): _cells(_select(result, case=case, law=law, method="semservo",
                                                                  stage_model="calibrated", frames=frames))
                                    for law in ("position", "paper") for frames in ("partial", "whole")}}
    return summary


def time_to_target_targets(result: dict) -> list[str]:
    """Issue #28's targets, per preset: met or not, with the number."""
    def mark(ok: bool) -> str:
        return "met" if ok else "**not met**"

    lines = ["| preset | median fresh frames <= 4 | worst <= 6 | true final error <= 0.1 px | N/N converged per cell | "
             "time >= 5 x shorter than the paper's law | no calibration or another stage's: N/N, frames <= 2 x |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for case, row in time_to_target_summary(result).items():
        position = row["position"]
        cells = [_cells(_select(result, case=case, offset=offset, law="position", method="semservo",
                                stage_model="calibrated")) for offset in result["offsets"]]
        all_converged = all(cell["converged"] == cell["n"] for cell in cells)
        others = [(model, other, ratio) for model, (other, ratio) in row["models"].items()]
        others_ok = all(other["converged"] == other["n"] and ratio <= 2.0 for _, other, ratio in others)
        worst_ratio = max((ratio for _, _, ratio in others), default=float("nan"))
        lines.append(
            f"| {CASE_NUMBERS.get(case, '')} {case} | {mark(position['fresh'] <= 4)}: {position['fresh']:g} | "
            f"{mark(position['fresh_max'] <= 6)}: {position['fresh_max']} | "
            f"{mark(position['error_max'] <= 0.1)}: {position['error_max']:.3f}{_resting(position)} | "
            f"{mark(all_converged)}: {min(c['converged'] for c in cells)}/{cells[0]['n']} at worst | "
            f"{mark(row['speedup'] >= 5)}: {row['speedup']:.1f} x | "
            f"{mark(others_ok)}: {min((o['converged'] for _, o, _ in others), default=0)}/{cells[0]['n'] * len(result['offsets'])}, "
            f"{worst_ratio:.2f} x at worst |")
    return lines


def _resting(cells: dict) -> str:
    """The stage's own worst error beside the frame's, where it was kept."""
    resting = cells.get("stage_error_max")
    return "" if resting is None else f" (resting: {resting:.3f})"


def time_to_target_lines(result: dict) -> list[str]:
    cell_help = ("Each cell: fresh frames used, median (worst) / frames scanned in all, median / simulated seconds to "
                 "the frame convergence was decided on, median / true final error, median (worst) / converged of N.")
    lines = [cell_help, "", "| preset | offset | position law | paper's law | time: paper / position |",
             "| --- | --- | --- | --- | --- |"]
    for case in result["cases"]:
        for offset in result["offsets"]:
            position = _cells(_select(result, case=case, offset=offset, law="position", method="semservo",
                                      stage_model="calibrated"))
            paper, _ = _paper_at_best(result, case=case, offset=offset, stage_model="calibrated")
            ratio = f"{paper['seconds'] / position['seconds']:.1f} x" if position and paper else "–"
            lines.append(f"| {CASE_NUMBERS.get(case, '')} {case} | {_offset_label(offset)} | {_law_cell(position)} | "
                         f"{_law_cell(paper)} | {ratio} |")
    return lines


def time_to_target_headline_lines(result: dict) -> list[str]:
    summary = time_to_target_summary(result)
    lines = ["| preset | position law: fresh frames, median (worst) | seconds, median (worst) | true final error, "
             "worst (px) | where the sample rested, worst (px) | converged | paper's law at its best: frames | "
             "fresh frames, median | seconds, median | converged | time: paper / position |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for case, row in summary.items():
        position, paper = row["position"], row["paper"]
        lines.append(f"| {CASE_NUMBERS.get(case, '')} {case} | {position['fresh']:g} ({position['fresh_max']}) | "
                     f"{position['seconds']:.2f} ({position['seconds_max']:.2f}) | {position['error_max']:.3f} | "
                     f"{'–' if position['stage_error_max'] is None else format(position['stage_error_max'], '.3f')} | "
                     f"{position['converged']}/{position['n']} | {row['paper_frames']} | {paper['fresh']:g} | "
                     f"{paper['seconds']:.1f} | {paper['converged']}/{paper['n']} | {row['speedup']:.1f} x |")
    return lines


def time_to_target_frames_lines(result: dict) -> list[str]:
    """Both laws on whole fresh frames and on partial frames (calibrated model): fresh
    frames and seconds, median (worst), and the true final error's worst."""
    lines = ["| preset | position law, partial frames (its default) | position law, whole frames | "
             "paper's law, whole frames (its default) | paper's law, partial frames |",
             "| --- | --- | --- | --- | --- |"]

    def cell(cells: dict) -> str:
        if not cells:
            return "–"
        return (f"{cells['fresh']:g} ({cells['fresh_max']}) frames, {cells['seconds']:.2f} ({cells['seconds_max']:.2f}) s, "
                f"{cells['error_max']:.3f} px, {cells['converged']}/{cells['n']}")
    for case, row in time_to_target_summary(result).items():
        frames = row["frames"]
        lines.append(f"| {CASE_NUMBERS.get(case, '')} {case} | {cell(frames[('position', 'partial')])} | "
                     f"{cell(frames[('position', 'whole')])} | {cell(frames[('paper', 'whole')])} | "
                     f"{cell(frames[('paper', 'partial')])} |")
    return lines


def time_to_target_model_lines(result: dict) -> list[str]:
    lines = ["| preset | stage model | position law: fresh frames, median (worst) | x calibrated (median) | "
             "true final error, worst (px) | overshoot, worst (px) | converged | paper's law: fresh frames, median "
             "| converged |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for case in result["cases"]:
        calibrated = _cells(_select(result, case=case, law="position", method="semservo", stage_model="calibrated"))
        for model in result["models"]:
            position = _cells(_select(result, case=case, law="position", method="semservo", stage_model=model))
            paper = _cells(_select(result, case=case, law="paper", method="semservo", stage_model=model))
            if not position:
                continue
            lines.append(f"| {CASE_NUMBERS.get(case, '')} {case} | {MODEL_LABELS[model]} | {position['fresh']:g} "
                         f"({position['fresh_max']}) | {position['fresh'] / calibrated['fresh']:.2f} | "
                         f"{position['error_max']:.3f} | {position['overshoot_max']:.2f} | "
                         f"{position['converged']}/{position['n']} | "
                         + (f"{paper['fresh']:g} | {paper['converged']}/{paper['n']} |" if paper else "– | – |"))
    return lines


def time_to_target_baseline_lines(result: dict) -> list[str]:
    lines = ["| preset | photometric DVS (paper's law): converged | seconds, median (of converged) | "
             "semservo, paper's law: seconds, median | semservo, position law: seconds, median |",
             "| --- | --- | --- | --- | --- |"]
    for case in result["cases"]:
        rows = _select(result, case=case, law="paper", method="photometric", stage_model="calibrated")
        if not rows:
            continue
        converged = [r for r in rows if r["outcome"] == "converged"]
        seconds = f"{np.median([r['seconds'] for r in converged]):.1f}" if converged else "–"
        paper = _cells(_select(result, case=case, law="paper", method="semservo", stage_model="calibrated"))
        position = _cells(_select(result, case=case, law="position", method="semservo", stage_model="calibrated"))
        lines.append(f"| {CASE_NUMBERS.get(case, '')} {case} | {len(converged)}/{len(rows)} | {seconds} | "
                     f"{paper['seconds']:.1f} | {position['seconds']:.1f} |")
    return lines


def plot_time_to_target(result: dict, path: Path) -> None:
    """True error against simulated time, both laws, one panel per preset (trial 1 of
    each offset, calibrated model)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = result["cases"]
    columns = min(4, len(cases))
    rows = math.ceil(len(cases) / columns)
    figure, axes = plt.subplots(rows, columns, figsize=(3.6 * columns, 3.0 * rows), squeeze=False)
    for ax, case in zip(axes.flat, cases):
        for offset_index, offset in enumerate(result["offsets"]):
            for law, style in (("position", "-"), ("paper", "--")):
                trials = [r for r in _select(result, case=case, offset=offset, law=law, method="semservo",
                                             stage_model="calibrated") if r.get("trace")]
                if not trials:
                    continue
                times, errors = zip(*[(t, max(e, 1e-3)) for t, e, _ in trials[0]["trace"]])
                ax.semilogy(times, errors, style, color=f"C{offset_index}", linewidth=1.2,
                            label=_offset_label(offset) if law == "position" else None)
        ax.axhline(0.1, color="grey", linewidth=0.8, linestyle=":")
        ax.set(title=case, xlabel="simulated time (s)", ylabel="true error (px)", ylim=(1e-3, 400))
        ax.set_xlim(left=0)
    for ax in list(axes.flat)[len(cases):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7, title="solid: position law\ndashed: paper's law", title_fontsize=7)
    figure.suptitle("Time to target: the true error (simulator) against simulated time, at each preset's frame rate")
    figure.tight_layout()
    figure.savefig(path, dpi=90)
    plt.close(figure)


def hold_lines(result: dict) -> list[str]:
    lines = ["| run | reached the target in | held for | corrections | true error while holding, worst (px) |",
             "| --- | --- | --- | --- | --- |"]
    for index, run in enumerate(result["runs"], 1):
        if run["outcome"] != "converged":
            lines.append(f"| {index} | did not converge: {run['reason']} | – | – | – |")
            continue
        lines.append(f"| {index} | {run['fresh_frames']} fresh frames, {run['seconds']:.1f} s | "
                     f"{run['hold_s'] / 60:.1f} min | {run['hold_corrections']} | {run['hold_worst_true_px']:.3f} |")
    return lines


def write(out: Path, say: Callable[[str], None] = print) -> Path:
    lines = ["# The paper, reproduced on the simulated lab", "",
             "Generated by `semservo reproduce` (also `./dev bench reproduce`) on "
             f"{time.strftime('%Y-%m-%d')}. Every number below is from the simulated lab (`services/fakelab`, the "
             "paper's presets); the paper's own numbers are beside them. Each trial is one closed loop in process "
             "(`semservo.reproduce.loop`): the simulated SEM and piezo stage (hysteresis, drift, vibration, noise), "
             "one motion measurement, the paper's control law (eq. 30-37); the true error is the simulator's "
             "pose at the end against the pose the reference was taught at. The whole-stack benchmarks "
             "(`bench/positioning.py`, `bench/tilt.py`) add the services and the serial line.", ""]
    # Experiments are kept between runs (resumable), so the report says when each was run:
    # one run again after a change (``--only NAME --fresh``) leaves the others as they were.
    results = {name: load(out, name) for name in EXPERIMENTS}
    runs = [f"{name} {result['finished_at'][:10]}" for name, result in results.items()
            if result and result.get("finished_at")]
    if runs:
        lines += ["Each experiment as last run (`semservo reproduce --only NAME --fresh` runs one again): "
                  + ", ".join(runs) + ".", ""]
    figures = []
    table4 = results["table4"]
    if table4:
        lines += ["## Table IV: time per iteration and successes", "",
                  f"Computation per iteration (the method's measurement, ms, mean) and converged trials out of "
                  f"{table4['trials']} per case, every method closing the same loop from the same starts (8-15 % "
                  "of the field away). One frame per iteration for every method (frame time: 0.4 s at 720 ns/px, "
                  "0.2 s at 360, 0.1 s at 180). Paper: ms on its 2013 PC (successes of 6; × all failed)."
                  + (f" Every method gets the same budget, {table4['budget_s']:g} s of simulated scanning (not a "
                     "number of iterations), and a trial counts only if it stopped within tolerance by its own "
                     f"measure with the simulator's true error under {table4['at_target_px']:g} px."
                     if "budget_s" in table4 else "")
                  + (" *Quick run: fewer cases and trials.*" if table4.get("quick") else ""), ""]
        lines += table4_lines(table4) + ["", "Where a method failed, the loop's reason:", ""]
        lines += failures(table4) or ["- none"]
        lines += ["", table4_summary(table4),
                  "", "Baseline settings (chosen once, not per case): see `semservo.reproduce.methods`. SIFT stands "
                  "in for the paper's SURF (patented; not in current OpenCV builds), ORB (oriented FAST) for FAST.", ""]
    timing = results["time_to_target"]
    if timing:
        quick = " *Quick run: fewer presets, models and trials.*" if timing.get("quick") else ""
        settings = timing["settings"]
        lines += ["## Time to target (not in the paper): the position law beside the paper's", "",
                  "What a microscopist feels is how long positioning takes. Each trial on a continuously scanning SEM "
                  "(`semservo.reproduce.loop.run_timed_trial`): a move is written "
                  f"{settings['latency_s'] * 1000:.0f} ms after a frame ends and lands during the next scan. On "
                  "whole frames that scan is not acted on, and the next frame scanned wholly after the move has "
                  "settled (the stage's settling model) is the next fresh one; on partial frames (the position "
                  "law's default) the rows of that scan scanned after the move settled are measured and acted on, "
                  "when they are at least half of it. Each law is run both ways and compared at its best (the "
                  "paper's law is slower on partial frames: its velocity law moves v t per frame, so more frequent "
                  "frames do not bring it sooner). Seconds at each preset's real frame rate. Starts 5, 15, 30 % of the "
                  f"field and half a pixel away, {timing['trials']} per cell in random directions, the same for both "
                  f"laws, each started {settings.get('start_after_s', 1.0):g}-"
                  f"{settings.get('start_after_s', 1.0) + settings.get('start_jitter_s', 0.0):g} s after its jog (a random part "
                  "from its seed: trials meet the stage's vibration at random phases); the paper's law's moves "
                  f"saturate at {settings['max_move_um']:g} um, the position law's at "
                  f"{settings.get('max_moves', 1)} x that once the stage has responded as commanded (made in "
                  f"pieces of at most {settings['max_move_um']:g} um); the paper's law converges when the mean of "
                  f"its last {settings['converge_frames']} fresh errors is within tolerance (the controller now asks "
                  "the mean of their sizes, which is stricter), the position law "
                  "on its own estimate (error plus one standard deviation within tolerance, now and as far as its "
                  "last move's creep goes in 10 s); tolerance "
                  f"{settings['tolerance_px']:g} px; a budget of {settings['time_budget_s']:g} simulated seconds."
                  + quick, "", "### Per preset (calibrated stage model, every offset)", "",
                  "The true final error is that of the frame convergence was decided on: its mean pose (over its scan) "
                  "against the reference's. Where the sample rested then, the vibration left out, is the stage's "
                  "own error: the frame's mean also holds the vibration's mean over that scan, which no move of "
                  "the stage removes (up to ~0.05 px at x5000, where the simulated lab's 10 nm at 7 Hz is 0.24 px).",
                  ""]
        lines += time_to_target_headline_lines(timing)
        lines += ["", "### Whole and partial frames, both laws", "", "Each law on the frames it uses by default and "
                  "on the other kind (calibrated model, every offset): fresh frames, median (worst); simulated "
                  "seconds, median (worst); the true final error's worst; converged of N. A partial frame counts "
                  "as a fresh frame.", ""]
        lines += time_to_target_frames_lines(timing)
        lines += ["", "### Issue #28's targets", "", "Frames, errors and convergence of the position law with the "
                  "calibrated model over every offset; time: the paper's law's median seconds over the position "
                  "law's; the last column over the three other stage models."] + [""]
        lines += time_to_target_targets(timing)
        lines += ["", "### Per preset and offset", ""] + time_to_target_lines(timing)
        lines += ["", "### Without a calibration, and with another stage's model", "",
                  "The stage service maps micrometres to volts with a linear model from the nominal stroke "
                  "(100 um over 150 V; the position law is told its gain is 70 % uncertain) or with the lab's model "
                  "for a stage that moves 15 % more or less than this one (the law believes it calibrated). "
                  "Overshoot: how far the content went past the target along the start's direction (true). The "
                  "paper's law without a calibration on fewer trials per cell (the N in its column)."]
        lines += [""] + time_to_target_model_lines(timing)
        baseline = time_to_target_baseline_lines(timing)
        if len(baseline) > 2:
            lines += ["", "### The photometric baseline's time to target", "",
                      "Its measurement (`methods.photometric_method`: Levenberg-Marquardt on an image pyramid) closing "
                      "the paper's law, the same starts, scanning and budget."] + [""] + baseline
        plot_time_to_target(timing, out / "time_to_target.png")
        lines += ["", "![Time to target: true error against simulated time](time_to_target.png)", ""]
    hold = results["hold"]
    if hold:
        lines += ["## Hold after arrival (not in the paper)", "",
                  f"The position law reaches the target from 5 % of the field under the `unstable` preset (levels "
                  f"changing, the lab's drift and vibration), then holds it for {hold['minutes']:g} simulated minute{'' if hold['minutes'] == 1 else 's'}: "
                  "the true error of every fresh frame while holding, and the corrections made.", ""]
        lines += hold_lines(hold) + [""]
    table3 = results["table3"]
    if table3:
        lines += ["## Table III: accuracy over trials", "",
                  f"semservo, {table3['trials']} trials per case; accuracy is the mean |true error| per axis; "
                  "RMSE and PSNR between the desired and the final image (8-bit, both levelled), for cases 1-3 as "
                  "in the paper." + (" *Quick run.*" if table3.get("quick") else ""), ""]
        lines += table3_lines(table3) + ["",
                  "RMSE and PSNR here are set by the simulator's shot noise between two independent frames (the "
                  "desired one averaged over 4 scans, the final one a single scan), not by misalignment: they are "
                  "worse than the paper's although the alignment is ten times better. The paper's pairs are not "
                  "consistent on an 8-bit scale either (PSNR 38.73 dB is an RMSE of 2.96, not 1.60).", ""]
        for case, trials in table3["rows"].items():
            name = f"runs_{case}.png"
            plot_runs(case, trials, out / name)
            figures.append((f"Figs. 9-11, case {CASE_NUMBERS[case]} ({case})", name))
    table2 = results["table2"]
    if table2:
        lines += ["## Table II: positioning error against the desired image's quality", "",
                  f"Reference scanned once per trial at the given dwell, live frames at 360 ns/px; {table2['trials']} "
                  "trial(s) each; mean |true error| per axis in pixels." + (" *Quick run.*" if table2.get("quick")
                                                                              else ""), ""]
        lines += table2_lines(table2) + ["",
                  "Unlike the paper's, the error here hardly depends on the reference's quality: the estimator's "
                  "whole-spectrum fit is limited by the live frames' noise and the stage's vibration, not by the "
                  "reference's.", ""]
    table1 = results["table1"]
    if table1:
        lines += ["## Table I: the tilts", "",
                  "The paper's three poses on the simulated `tilts` preset (depth of field 3.5 um), the plane fit "
                  "to the focus sweep's kernel depths and gamma on the frame seen square on; the paper's errors reach "
                  "0.82 degree with a sign flip at 3 degrees. 30 random poses, both methods and the 5-DOF runs of "
                  "Fig. 8 (10/10 converged from random poses, through the whole stack): `./dev bench tilt` and the "
                  "main README's *Five degrees of freedom*, with its plot `docs/tilt_fig8.png`.", ""]
        lines += table1_lines(table1) + [""]
    replay = results["replay2013"]
    if replay:
        lines += ["## The 2013 recording against the photometric baseline", ""]
        if "skipped" in replay:
            lines += [f"(not run: {replay['skipped']})", ""]
        else:
            lines += [f"The real 2013 run ({replay['frames']} frames) was driven by photometric visual servoing. Its "
                      "recorded stage increment per iteration against our photometric method's step on the same "
                      "frames, and against semservo's measured error (the run's path), as correlation coefficients "
                      "(the recording's axis signs are its own; rows and frames align to about one frame):", "",
                      "| axis | ours vs recorded, all frames | last 23 frames | semservo's error vs recorded, all | "
                      "last 23 |", "| --- | --- | --- | --- | --- |"]
            for axis in ("x", "y"):
                lines.append(f"| {axis} | {replay['correlation_' + axis]:+.2f} | {replay['correlation_' + axis + '_last']:+.2f} "
                             f"| {replay['error_correlation_' + axis]:+.2f} | "
                             f"{replay['error_correlation_' + axis + '_last']:+.2f} |")
            lines += ["", "A weak check: the recording's increments follow our photometric step about as well as they "
                      "follow the measured error itself, best near the end where the run oscillates. Far from the "
                      "goal (40-55 px) our step on frames halved twice is small while the recorded law moved steadily: "
                      "its gain and image scale are not recorded.", ""]
    fig8 = results["fig8"]
    if fig8:
        lines += ["## Fig. 8: five degrees of freedom", ""]
        lines += ["Through the whole stack (the fake lab 20 times faster), each run from the taught pose; the true "
                  "final errors from the simulator.", "",
                  "| from alpha, beta, gamma (deg), x, y (um) | outcome | iterations | true final alpha, beta, "
                  "gamma (deg) | x, y (px) |", "| --- | --- | --- | --- | --- |"]
        for run in fig8["runs"]:
            error, (a, b, g, x, y) = run["truth"].get("error_deg", {}), run["initial"]
            lines.append(f"| {a:+.1f}, {b:+.1f}, {g:+.1f}, {x:+.1f}, {y:+.1f} | {run['state']} | "
                         f"{run['iterations']} | {error.get('tilt_x_deg', math.nan):+.3f}, "
                         f"{error.get('tilt_y_deg', math.nan):+.3f}, {error.get('rotation_deg', math.nan):+.4f} | "
                         f"{run['truth'].get('error_norm_px', math.nan):.2f} |")
        lines.append("")
        plot_fig8(fig8["runs"][0], out / "fig8_five_dof.png")
        figures.append(("Fig. 8: angular velocities and cost per iteration, from (7, 12, 20) degrees",
                        "fig8_five_dof.png"))
    fig4 = results["fig4"]
    if fig4:
        plot_fig4(fig4, out / "fig4_cost_map.png")
        figures.insert(0, ("Fig. 4: the cost around the desired pose", "fig4_cost_map.png"))
    if figures:
        lines += ["## Figures", ""]
        for title, name in figures:
            lines += [f"### {title}", "", f"![{title}]({name})", ""]
    path = out / "README.md"
    path.write_text("\n".join(lines) + "\n")
    say(f"report: {path}")
    return path


__all__ = ["write", "PAPER_TABLE1_POSES"]
