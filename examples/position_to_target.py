"""Position to a taught target from a displaced start (the paper's experiment).

Run the system first (`./dev up`), then: `.venv/bin/python examples/position_to_target.py`
"""

from semservo.client import Client

with Client() as lab:  # http://127.0.0.1:8000; a token comes from $SEMSERVO_API_TOKEN
    target = lab.teach(frames=4)  # the live view, averaged over 4 frames
    print("taught", target.id)
    lab.move(x_um=8.0, y_um=-5.0)  # somewhere else, as with the joystick
    run = lab.start(tolerance_px=0.1)
    result = lab.wait(run.run_id, timeout=300, stop_on_timeout=True)
    print(f"{result.state} after {result.iterations} iterations ({result.fresh_frames} fresh frames, "
          f"{result.duration_s:.1f} s), estimated error {result.final_error_px:.3f} px")
    if result.truth:  # simulated hardware knows the truth
        print(f"true error {result.truth['error_norm_px']:.3f} px")
