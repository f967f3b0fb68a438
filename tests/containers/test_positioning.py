"""A lab script positions the stage through the gateway's published port; the true final
error comes from the fake lab's container (the gateway asks it over the simulator
network), not from the estimate the loop converged on."""

from __future__ import annotations


def test_a_positioning_run_through_the_published_port_converges(system, lab):
    run = system.displace_and_start(lab, offset=(6.0, -4.0), tolerance_px=0.2)
    result = lab.wait(run["run_id"], timeout=240)

    assert result["state"] == "converged", result["reason"]
    assert result["final_error_px"] <= 0.2
    truth = result["truth"]
    assert truth is not None, result.get("outcome")
    # A 6 x 4 um jog is ~40 px at this magnification: back within a pixel, truly.
    assert truth["error_norm_px"] < 1.0, truth
    assert max(abs(value) for value in truth["error_um"]) < 0.2, truth
    # Every move went through the stage service and the serial link to the amplifier.
    assert any(entry["text"].startswith("set,") for entry in result["stage_commands"])
