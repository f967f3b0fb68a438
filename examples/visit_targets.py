"""Visit a list of taught targets in turn: teach each one where the stage stands, then
go back to each from wherever the previous run ended.

Run the system first (`./dev up`), then: `.venv/bin/python examples/visit_targets.py`
"""

from pathlib import Path

from semservo.client import Client

OFFSETS_UM = [(0.0, 0.0), (10.0, 0.0), (10.0, -8.0)]  # where to teach each target, from the start
folder = Path("targets")
folder.mkdir(exist_ok=True)

with Client() as lab:
    targets = []
    for index, (x_um, y_um) in enumerate(OFFSETS_UM):
        if index:
            previous = OFFSETS_UM[index - 1]
            lab.move(x_um=x_um - previous[0], y_um=y_um - previous[1])
        # Keep each target as an image: teaching it again later is an upload.
        path = folder / f"target-{index}.png"
        path.write_bytes(lab.http.get("/frames/latest.png").content)
        targets.append(path)
    for path in reversed(targets):
        lab.teach(image=path, label=path.name)
        run = lab.start(tolerance_px=0.15)
        result = lab.wait(run["run_id"], timeout=300)
        print(f"{path.name}: {result['state']} in {result['iterations']} iterations")
