"""A lab script that already drives its microscope through OpenFIBSEM, positioning it
with semservo: the lines between the ``semservo`` markers are all it adds.

    pip install -e '.[openfibsem]'
    python examples/openfibsem_position.py        # on OpenFIBSEM's DemoMicroscope

On a Thermo Fisher or TESCAN microscope: ``setup_session`` with its manufacturer and
address (and its configuration), without the line marked "demo only"; see
docs/instruments.md ("OpenFIBSEM") for the first run at a small step.
"""

import os
import tempfile

os.environ.setdefault("FIBSEM_SIM_NO_DELAY", "1")  # the demo pretends each stage move takes a second

from fibsem import utils
from fibsem.structures import BeamType

from semservo.openfibsem import SimulatedDemoFrames

microscope, settings = utils.setup_session(session_path=tempfile.mkdtemp(), manufacturer="Demo",
                                           ip_address="localhost", setup_logging=False)
SimulatedDemoFrames(microscope)  # demo only: its frames see a sample that follows its stage and beam shift

# --- semservo ---
from semservo.openfibsem import Positioner

positioner = Positioner(microscope, hfw_um=90.0, dwell_ns=720)
positioner.teach(frames=4)  # the view now is the target
# --- end semservo ---

microscope.stable_move(dx=12e-6, dy=-8e-6, beam_type=BeamType.ELECTRON)  # the script moves on, or the sample drifts

# --- semservo ---
run = positioner.run(beam_shift_within_um=2.0)  # back to it: the stage, then the beam shift for the last um
print(f"{run['outcome']['state']}: {run['outcome']['reason']} ({run['iterations']} moves)")
# --- end semservo ---
