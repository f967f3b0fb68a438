"""Visit a list of taught targets in turn: teach each one where the stage stands, then
go back to each from wherever the previous run ended.

Run the system first (`./dev up`), then: `.venv/bin/python examples/visit_targets.py`
"""

import time
from pathlib import Path

from semservo.client import Client

OFFSETS_UM = [(0.0, 0.0), (10.0, 0.0), (10.0, -8.0)]  # where to teach each target, from the start
folder = Path("targets")
folder.mkdir(exist_ok=True)



def frame_after_move(lab: Client) -> bytes:
    """The live image once a whole frame was scanned after the move (the frame being
    scanned while the stage moved shows a mix of both places)."""
    seq = lab.status()["latest_frame_seq"]
    while lab.status()["latest_frame_seq"] < seq + 2:
        time.sleep(0.1)
    return lab.http.get("/frames/latest.png").content


with Client() as lab:
    targets = []
    for index, (x_um, y_um) in enumerate(OFFSETS_UM):
        if index:
            previous = OFFSETS_UM[index - 1]
            lab.move(x_um=x_um - previous[0], y_um=y_um - previous[1])
        # Keep each target as an image: teaching it again later is an upload.
        path = folder / f"target-{index}.png"
        path.write_bytes(frame_after_move(lab))
        targets.append(path)
    for path in reversed(targets):
        lab.teach(image=path, label=path.name)
        run = lab.start(tolerance_px=0.15)
        result = lab.wait(run["run_id"], timeout=300)
        truth = f", true error {result['truth']['error_norm_px']:.2f} px" if result.get("truth") else ""
        print(f"{path.name}: {result['state']} in {result['iterations']} iterations{truth}")
