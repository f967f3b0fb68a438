"""Tilt benchmark, on the simulated SEM (paper Table I and Fig. 8, issue #15).

Part 1, Table I: the out-of-plane tilts alpha (about x) and beta (about y) and the
rotation about the beam gamma, measured on the simulated SEM's ``tilts`` preset (x3000,
a 3.5 um depth of field, gold on carbon) against a reference taught at (0, 0, 0): the
paper's three poses (15, -15, 70), (8, -8, 30), (3, 3, -5) degrees and ``--poses``
random ones within +-15 degrees of tilt and +-90 of gamma. For each pose:

* the tilts by both methods from the same focus sweeps: the robust plane fit
  (semservo's default) and the paper's extended Gaussian image correlation (eq. 14-17);
  first from a wide sweep (nothing known), then from a tracking sweep planned from the
  first measurement on the taught sweep's grid (what a run uses after its first sweep);
* gamma from one frame at the nominal focus, raw and with the measured tilts' foreshortening
  undone first;
* frames, simulated scan time and compute time per measurement.

Part 2, Fig. 8: 5-DOF runs through the whole stack (real services, the fake lab sped up):
from (alpha, beta, gamma) = (7, 12, 20) degrees plus a translation (the paper's Fig. 8),
then ``--runs`` runs from random poses; each must converge, with the true final errors
from the simulator. Plotted like the paper: angular velocities and cost per iteration.

The measurements live in :mod:`semservo.reproduce.tilts` (``semservo reproduce`` runs
them too); this script runs them at full size and prints the tables.

Part 3 (``--sample-images``): only the 5-DOF runs, repeated with real SEM pictures as
the sample (``semservo.simulation.sample_image``, under the tilts preset's optics and as
if photographed at its pixel), each scene from the same random starts, tolerance 0.1 px;
``scene`` is the preset's own scene with the same settings. The view error (where the
content at the taught view's centre is) is reported beside the stage's.

Tuning caveat: the simulator and the methods were developed together, on this one
simulated scene; these are simulated results, not a real instrument's.

    ./dev bench tilt                 # or: python bench/tilt.py --poses 30 --runs 10
    ./dev bench tilt --sample-images scene jeol_grid fibsem_slice_cells hole_low_mag tescan_aperture
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

import numpy as np

from semservo import jsontext
from semservo.reproduce.tilts import (DEPTH_OF_FIELD_UM, FIG8_START, PAPER_POSES, PAPER_WORST_DEG,
                                      depth_of_field_scan, five_dof_runs, plot_fig8, random_starts, summarize,
                                      table_one)

RESULTS = Path(__file__).parent / "results"


def say(text: str = "") -> None:
    print(text, flush=True)


def print_table_one(result: dict, summary: dict) -> None:
    say("\n### Table I: per pose, error (measured - true, degrees)\n")
    say("| alpha, beta, gamma (true) | plane alpha | plane beta | EGI alpha | EGI beta | gamma raw | gamma compensated |")
    say("| --- | --- | --- | --- | --- | --- | --- |")
    for row in result["rows"][:len(PAPER_POSES)]:
        a, b, g = row["pose"]
        say(f"| ({a:g}, {b:g}, {g:g}) | {row['plane'][0]:+.3f} | {row['plane'][1]:+.3f} | {row['egi'][0]:+.3f} | "
            f"{row['egi'][1]:+.3f} | {row['gamma_raw']:+.4f} | {row['gamma_compensated']:+.4f} |")
    say(f"\n### All {len(result['rows'])} poses: |error| mean / max (degrees); paper: up to {PAPER_WORST_DEG}, a sign "
        "flip at 3 degrees\n")
    say("| method | alpha | beta | sign errors (true >= 0.5 deg) | frames | scan time (s, simulated) | compute (ms) |")
    say("| --- | --- | --- | --- | --- | --- | --- |")
    for method, label, frames, compute in (("plane", "plane fit, first sweep (default)", "frames_first", "plane_ms"),
                                           ("plane_tracking", "plane fit, tracking sweep", "frames_tracking", None),
                                           ("egi", "paper's EGI correlation, first sweep", "frames_first", "egi_ms")):
        entry = summary[method]
        signs = (f"{entry['sign_errors']} of {entry['signs_checked']}" if "sign_errors" in entry else "")
        scan = summary["scan_s_first" if frames == "frames_first" else "scan_s_tracking"]
        timing = f"{summary[compute]['mean']:.0f} (max {summary[compute]['max']:.0f})" if compute else ""
        say(f"| {label} | {entry['alpha']['mean']:.3f} / {entry['alpha']['max']:.3f} | "
            f"{entry['beta']['mean']:.3f} / {entry['beta']['max']:.3f} | {signs} | "
            f"{summary[frames]['mean']:.1f} (max {summary[frames]['max']:.0f}) | {scan['mean']:.1f} | {timing} |")
    say(f"| gamma, raw frame | {summary['gamma_raw']['mean']:.4f} / {summary['gamma_raw']['max']:.4f} | | | 1 | | |")
    say(f"| gamma, foreshortening undone | {summary['gamma_compensated']['mean']:.4f} / "
        f"{summary['gamma_compensated']['max']:.4f} | | | 1 | | |")


def print_runs(runs: list[dict], first: str | None = "Fig. 8") -> None:
    """The runs' table: the first labelled ``first`` and the rest numbered from 1 (all
    numbered from 1 when ``first`` is None)."""
    say("\n| run | from alpha, beta, gamma (deg), x, y (um) | outcome | iterations | sweeps acted on | "
        "true error alpha, beta, gamma (deg) | stage x, y (px) | view x, y (px) |")
    say("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for index, run in enumerate(runs):
        error = run["truth"].get("error_deg", {})
        view = run.get("view_error_px")
        a, b, g, x, y = run["initial"]
        label = index + 1 if first is None else (first if index == 0 else index)
        say(f"| {label} | {a:+.1f}, {b:+.1f}, {g:+.1f}, {x:+.1f}, {y:+.1f} | "
            f"{run['state']} | {run['iterations']} | {run['tilt_iterations']} | "
            f"{error.get('tilt_x_deg', math.nan):+.3f}, {error.get('tilt_y_deg', math.nan):+.3f}, "
            f"{error.get('rotation_deg', math.nan):+.4f} | {run['truth'].get('error_norm_px', math.nan):.2f} | "
            + (f"{view[0]:+.3f}, {view[1]:+.3f} |" if view else "- |"))


def summarize_runs(runs: list[dict]) -> dict:
    """Converged count, iterations, and the true final errors' mean and max: tilts
    (degrees), gamma, and the view's x, y (px)."""
    ok = [run for run in runs if run["state"] == "converged"]

    def stats(values):
        values = np.abs([value for value in values if value is not None and math.isfinite(value)])
        return {"mean": float(values.mean()), "max": float(values.max())} if len(values) else None

    return {"converged": len(ok), "runs": len(runs),
            "iterations": float(np.mean([run["iterations"] for run in ok])) if ok else None,
            "wall_s": float(np.mean([run["wall_s"] for run in ok])) if ok else None,
            "tilt_deg": stats([run["truth"].get("error_deg", {}).get(key) for run in ok
                               for key in ("tilt_x_deg", "tilt_y_deg")]),
            "gamma_deg": stats([run["truth"].get("error_deg", {}).get("rotation_deg") for run in ok]),
            "view_px": stats([value for run in ok for value in (run.get("view_error_px") or [])]),
            "stage_px": stats([run["truth"].get("error_norm_px") for run in ok])}


def sample_image_runs(args, rng: np.random.Generator) -> int:
    """The 5-DOF runs on real pictures as the sample, under the tilts preset's optics and
    as if photographed at its scan pixel, each scene with the same random starts."""
    from semservo.client import SemservoError
    from semservo.simulation.sample_image import find_picture, scan_pixel_um
    from semservo.simulation.world import PRESETS

    starts = random_starts(rng, args.runs)
    pixel_nm = scan_pixel_um(PRESETS["tilts"].magnification, 512) * 1000
    tolerance = 0.1 if args.tolerance_px is None else args.tolerance_px
    output = {"run_settings": {"tolerance_px": tolerance, "converge_on": args.converge_on, "law": args.law},
              "scenes": {}}
    for name in args.sample_images:
        environment = {}
        if name != "scene":
            image = find_picture(name)
            name = image.stem
            environment = {"SEMSERVO_FAKELAB__SAMPLE_IMAGE": str(image),
                           "SEMSERVO_FAKELAB__SAMPLE_PIXEL_SIZE_NM": f"{pixel_nm:.6g}"}
        say(f"\n{name}: {len(starts)} 5-DOF runs through the whole stack (fake lab x{args.speedup:g}, tilts preset's "
            f"optics, tolerance {tolerance:g} px)")
        try:
            folder = None
            if args.records:  # the system's folder kept: each run's record and journal in runs/
                folder = args.records / name
                folder.mkdir(parents=True, exist_ok=True)
            runs = five_dof_runs(starts, folder, speedup=args.speedup, say=say, environment=environment,
                                 run_settings={"tolerance_px": tolerance, "converge_on": args.converge_on,
                                               "law": args.law})
        except SemservoError as error:  # e.g. a picture whose focus sweep cannot tell the tilts
            say(f"{name}: refused: {error}")
            output["scenes"][name] = {"refused": str(error)}
            continue
        print_runs(runs, first=None)
        summary = summarize_runs(runs)
        say(f"{name}: {summary['converged']}/{summary['runs']} converged; true final tilts {summary['tilt_deg']}, "
            f"gamma {summary['gamma_deg']}, view {summary['view_px']} px")
        output["scenes"][name] = {"summary": summary, "runs": [{key: value for key, value in run.items()
                                                                 if key != "trajectory"} for run in runs]}
        (RESULTS / f"tilt-sample-images-{args.converge_on}.json").write_text(jsontext.dumps(output, indent=1))
    say("\n| scene | converged | iterations | true final tilts mean / max (deg) | gamma mean / max (deg) | "
        "view x, y mean / max (px) |")
    say("| --- | --- | --- | --- | --- | --- |")
    for name, scene in output["scenes"].items():
        if "refused" in scene:
            say(f"| {name} | refused: {scene['refused']} | | | | |")
            continue
        summary = scene["summary"]

        def cell(entry, digits=3):
            return f"{entry['mean']:.{digits}f} / {entry['max']:.{digits}f}" if entry else "-"

        say(f"| {name} | {summary['converged']}/{summary['runs']} | {summary['iterations'] or math.nan:.0f} | "
            f"{cell(summary['tilt_deg'])} | {cell(summary['gamma_deg'], 4)} | {cell(summary['view_px'])} |")
    say(f"\nwrote {RESULTS / f'tilt-sample-images-{args.converge_on}.json'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--poses", type=int, default=30, help="random poses besides the paper's three")
    parser.add_argument("--runs", type=int, default=10, help="5-DOF runs from random poses (0: none)")
    parser.add_argument("--speedup", type=float, default=20.0, help="simulated time runs this much faster")
    parser.add_argument("--seed", type=int, default=15)
    parser.add_argument("--dof-poses", type=int, default=10, help="poses for the depth-of-field scan (0: none)")
    parser.add_argument("--sample-images", nargs="+", metavar="IMAGE",
                        help="only the 5-DOF runs, on real pictures as the sample (files, or names of "
                             "../shared/data/sem-images; 'scene' for the tilts preset's own scene, with the same "
                             "settings); writes tilt-sample-images-{mean,each}.json")
    parser.add_argument("--tolerance-px", type=float, default=None,
                        help="the runs' x, y tolerance (default 0.3 px; 0.1 with --sample-images)")
    parser.add_argument("--law", choices=["paper", "position"], default="paper",
                        help="the law of the 5-DOF runs, x, y, rotation and tilts (default: the paper's, as the README's "
                             "tables; position: the controller's default)")
    parser.add_argument("--records", type=Path, default=None, metavar="DIR",
                        help="with --sample-images: keep each scene's system folder (its runs' records and journals, "
                             "runs/<id>.json and .jsonl) in DIR/<scene> instead of a temporary folder")
    parser.add_argument("--converge-on", choices=["mean", "each"], default="mean",
                        help="with --sample-images: converged when the mean of the last frames' errors is within "
                             "tolerance (default), or each one")
    args = parser.parse_args(argv)
    RESULTS.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    if args.sample_images:
        return sample_image_runs(args, rng)
    poses = PAPER_POSES + [(float(rng.uniform(-15, 15)), float(rng.uniform(-15, 15)), float(rng.uniform(-90, 90)))
                           for _ in range(args.poses)]
    say(f"Table I: {len(poses)} poses on the simulated SEM's tilts preset (x3000, depth of field "
        f"{DEPTH_OF_FIELD_UM} um), each against a reference at (0, 0, 0)")
    table = table_one(poses, args.seed, say=say)
    summary = summarize(table)
    print_table_one(table, summary)
    output = {"table_one": table, "summary": summary}
    if args.dof_poses:
        say(f"\nDepth of field: the plane fit on {args.dof_poses} of the poses as the depth of field grows "
            "(smaller aperture)")
        scan = depth_of_field_scan(poses[:args.dof_poses], args.seed, say=say)
        say("\n| depth of field (um) | frames | |error| mean / max (deg) | sign errors | refused |")
        say("| --- | --- | --- | --- | --- |")
        for row in scan:
            say(f"| {row['depth_of_field_um']:g} | {row['frames']} | {row['mean']:.3f} / {row['max']:.3f} | "
                f"{row['sign_errors']} of {row['signs_checked']} | {row['refused']} of {row['poses']} |")
        output["depth_of_field"] = scan
    if args.runs:
        initial = [FIG8_START] + random_starts(rng, args.runs)
        say(f"\nFig. 8: {len(initial)} 5-DOF runs through the whole stack (fake lab x{args.speedup:g})")
        runs = five_dof_runs(initial, speedup=args.speedup, say=say, run_settings={"law": args.law})
        plot_fig8(runs[0], RESULTS / "tilt_fig8.png")
        converged = sum(run["state"] == "converged" for run in runs[1:])
        say(f"\n{converged}/{len(runs) - 1} random runs converged (plus the Fig. 8 run: {runs[0]['state']}); "
            f"plot: {RESULTS / 'tilt_fig8.png'}")
        print_runs(runs)
        output["runs"] = [{key: value for key, value in run.items() if key != "trajectory" or index == 0}
                          for index, run in enumerate(runs)]
    (RESULTS / "tilt.json").write_text(jsontext.dumps(output, indent=1))
    say(f"\nwrote {RESULTS / 'tilt.json'}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    raise SystemExit(main())
