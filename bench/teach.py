"""How far a teach's tilts are off, against what their standard errors say: teaches with
tilts through the whole stack (real services on loopback, the fake lab's tilts preset sped
up), the stage untilted at its start pose, on the simulator's scene and on real SEM
pictures as the sample (``--scenes``: names in ``../shared/data/sem-images`` or files).
Before each teach the stage undoes the drift since the first (as an operator re-centres
the view), so every teach sees the same part of the picture.

Why it matters: a run servoes the tilts onto the taught reading, so the teach's error is
carried by every run from it, and the standard errors the teach reports
(``alpha_uncertainty_deg``, ``beta_uncertainty_deg``: the jackknife over the kernels,
pooled over the teach's sweeps) are all a user has to judge it by. Per scene: the mean
error and its spread, the mean standard error, and the errors in standard errors (RMS
about 1 when the standard errors are right, under 1 when cautious; the largest). The
truth is the simulator's, over the taught frames' scans.

    ./dev bench teach                                     # 10 teaches on three pictures
    ./dev bench teach --scenes scene jeol_grid --teaches 20

Writes bench/results/teach.json.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from semservo import jsontext
from semservo.reproduce.tilts import repeated_teaches, summarize_teaches

RESULTS = Path(__file__).parent / "results"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    parser.add_argument("--scenes", nargs="+", default=["tescan_aperture", "jeol_grid", "hole_low_mag"],
                        metavar="SCENE", help="'scene' (the simulator's own), a picture's name in "
                                              "../shared/data/sem-images, or a file")
    parser.add_argument("--teaches", type=int, default=10, help="teaches per scene")
    parser.add_argument("--speedup", type=float, default=20.0, help="simulated time runs this much faster")
    args = parser.parse_args(argv)
    if args.teaches < 1:
        parser.error("--teaches must be at least 1")

    from semservo.simulation.sample_image import find_picture, scan_pixel_um
    from semservo.simulation.world import PRESETS

    pixel_nm = scan_pixel_um(PRESETS["tilts"].magnification, 512) * 1000
    output = {"teaches_per_scene": args.teaches, "speedup": args.speedup, "scenes": {}}
    for name in args.scenes:
        environment = {}
        if name != "scene":  # photographed at the preset's scan pixel, as bench/tilt.py's runs
            image = find_picture(name)
            name = image.stem
            environment = {"SEMSERVO_FAKELAB__SAMPLE_IMAGE": str(image),
                           "SEMSERVO_FAKELAB__SAMPLE_PIXEL_SIZE_NM": f"{pixel_nm:.6g}"}
        print(f"\n{name}: {args.teaches} teaches with tilts at rest (fake lab x{args.speedup:g}, tilts preset)",
              flush=True)
        teaches = repeated_teaches(args.teaches, args.speedup, lambda text: print(text, flush=True),
                                   environment=environment)
        output["scenes"][name] = {"summary": summarize_teaches(teaches), "teaches": teaches}
        RESULTS.mkdir(exist_ok=True)
        (RESULTS / "teach.json").write_text(jsontext.dumps(output, indent=1))
    print("\n| scene | taught | sweeps | alpha error mean / sd (deg) | its standard error | RMS / max z "
          "| beta error mean / sd (deg) | its standard error | RMS / max z |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for name, scene in output["scenes"].items():
        summary = scene["summary"]
        cells = []
        for axis in ("alpha", "beta"):
            entry = summary[axis]
            cells += [f"{entry['mean_error_deg']:+.3f} / {entry['sd_error_deg']:.3f}",
                      f"{entry['mean_uncertainty_deg']:.3f}", f"{entry['rms_z']:.2f} / {entry['max_abs_z']:.2f}"]
        print(f"| {name} | {summary['teaches'] - summary['refused']}/{summary['teaches']} | "
              f"{summary['sweeps_mean']:.1f} | " + " | ".join(cells) + " |")
    print(f"\nwrote {RESULTS / 'teach.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
