"""Visit a list of stored targets in turn: store a target where the stage stands (its
image, the stage's pose and the acquisition, under a name), move on, store the next;
then go back to each from wherever the previous run ended. The targets stay in the
gateway's records: a script days later can go back to them by name, or carry one to
another microscope PC as a file (`lab.export_target`, `lab.import_target`).

Run the system first (`./dev up`), then: `.venv/bin/python examples/visit_targets.py`
"""

import time

from semservo.client import Client

OFFSETS_UM = [(0.0, 0.0), (10.0, 0.0), (10.0, -8.0)]  # where to store each target, from the start


def settle(lab: Client) -> None:
    """Wait for two whole frames scanned after the move (the one being scanned while the
    stage moved shows a mix of both places)."""
    seq = lab.status().latest_frame_seq
    while lab.status().latest_frame_seq < seq + 2:
        time.sleep(0.1)


with Client() as lab:
    names = []
    for index, (x_um, y_um) in enumerate(OFFSETS_UM):
        if index:
            previous = OFFSETS_UM[index - 1]
            lab.move(x_um=x_um - previous[0], y_um=y_um - previous[1])
            settle(lab)
        lab.teach(frames=2)
        target = lab.save_target(f"target-{index}", note=f"{x_um:+g}, {y_um:+g} um from the start", replace=True)
        names.append(target.name)
    for name in reversed(names):
        run = lab.go_to_target(name, tolerance_px=0.15)  # the stored pose first, then the image
        result = lab.wait(run.run_id, timeout=300, stop_on_timeout=True)
        truth = f", true error {result.truth['error_norm_px']:.2f} px" if result.truth else ""
        print(f"{name}: {result.state} in {result.iterations} iterations{truth}")
