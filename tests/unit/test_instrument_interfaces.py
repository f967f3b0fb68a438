"""The two instrument interfaces: a lab's image-source adapter, found by dotted path
or entry point, and stage drivers, whose every one gets the stage's safety rules."""

from __future__ import annotations

import time

import numpy as np
import pytest

from semservo.instruments import (IMAGE_SOURCE_GROUP, NotReady, NotSupported, PluginError, SourceUnavailable,
                                  StageDriver, load_plugin)
from semservo.nv40_driver import NV403Driver
from semservo.simulation.amplifier import SimulatedAmplifier
from services.imageserver.sources import BackgroundAcquisition, adapter_source
from services.stage.core import Refused, StageCore, StageLimits, driver_class

ADAPTER = "examples.adapters.pattern_sem:PatternSEM"


def next_image(source, timeout_s: float = 10.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            return source.acquire()
        except NotReady:
            time.sleep(0.005)
    raise AssertionError("no frame from the adapter")


def test_an_adapter_by_dotted_path_delivers_frames_with_its_metadata():
    source = adapter_source(ADAPTER, {"rows": 64, "cols": 96, "pixel_size_nm": 12.0}, fps=200)
    try:
        assert isinstance(source, BackgroundAcquisition)  # a blocking adapter runs in a thread of its own
        image = next_image(source)
        assert image.pixels.shape == (64, 96) and image.pixels.dtype == np.uint16
        assert image.acquisition() == {"pixel_size_nm": 12.0, "dwell_ns": 200.0, "working_distance_mm": 10.0,
                                       "detector": "SE", "instrument": "example pattern SEM"}
        assert source.describe()["adapter"] == ADAPTER
    finally:
        source.close()


def test_an_adapters_failures_reach_health_and_frames_continue():
    source = adapter_source(ADAPTER, {"rows": 64, "cols": 64, "fail_every": 2}, fps=200)
    try:
        errors, frames = 0, 0
        deadline = time.monotonic() + 15
        while (errors == 0 or frames < 2) and time.monotonic() < deadline:
            try:
                source.acquire()
                frames += 1
            except SourceUnavailable as error:
                assert "failed (the instrument's API raised)" in str(error)
                errors += 1
            except NotReady:
                time.sleep(0.005)
        assert errors >= 1 and frames >= 2
    finally:
        source.close()


def test_unknown_adapters_are_refused_saying_why():
    with pytest.raises(PluginError, match="cannot import 'no_such_lab.sem'"):
        load_plugin("no_such_lab.sem:Thing", IMAGE_SOURCE_GROUP)
    with pytest.raises(PluginError, match="has no 'Nothing'"):
        load_plugin("examples.adapters.pattern_sem:Nothing", IMAGE_SOURCE_GROUP)
    with pytest.raises(PluginError, match="neither a known name"):
        load_plugin("vendorx", IMAGE_SOURCE_GROUP)
    with pytest.raises(TypeError, match="not an image source"):
        adapter_source("semservo.instruments:PluginError", {}, fps=10)


def test_the_adapters_optional_capabilities():
    adapter = load_plugin(ADAPTER, IMAGE_SOURCE_GROUP)(rows=32, cols=32)
    assert adapter.set_working_distance(4.5) == 4.5 and adapter.acquire().working_distance_mm == 4.5
    from semservo.instruments import ImageSourceAdapter, NotSupported

    class FramesOnly(ImageSourceAdapter):
        def acquire(self):
            return None

    with pytest.raises(NotSupported, match="cannot set the focus"):
        FramesOnly().set_working_distance(3.0)
    with pytest.raises(TypeError, match="abstract"):
        ImageSourceAdapter()  # an adapter without acquire cannot even be made


# -- stage drivers --------------------------------------------------------------------------
def test_both_drivers_have_the_stage_driver_interface():
    assert driver_class("nv40") is NV403Driver and driver_class("simulated") is SimulatedAmplifier
    for cls in (NV403Driver, SimulatedAmplifier):
        for method in ("open", "identify", "take_control", "release", "output_limits", "read_outputs",
                       "write_outputs", "halt", "close"):
            assert callable(getattr(cls, method)), (cls, method)
    assert isinstance(SimulatedAmplifier.open("sim://interface"), StageDriver)
    assert driver_class("semservo.simulation.amplifier:SimulatedAmplifier") is SimulatedAmplifier


class Clock:
    now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def stage(request):
    url = f"sim://{request.node.name}"
    SimulatedAmplifier.devices.pop(url, None)
    clock = Clock()
    core = StageCore(url, limits=StageLimits(max_rate_v_per_s=1e6), clock=clock, open_driver=SimulatedAmplifier.open)
    assert core.connect()
    yield core, SimulatedAmplifier.devices[url], clock
    core.close()


def test_the_stage_moves_a_simulated_amplifier_through_the_model(stage):
    core, device, _ = stage
    assert core.device["model"] == "simulated amplifier" and device.remote[0] and device.remote[1]
    start = core.positions()
    result = core.move({"x": 2.0, "y": 1.0}, relative=True)
    assert device.outputs[0] == pytest.approx(result["voltages"]["x"]) and result["voltages"]["x"] > 0
    assert core.positions()["x"] == pytest.approx(start["x"] + 2.0)
    assert core.positions()["y"] == pytest.approx(start["y"] + 1.0)


def test_every_safety_rule_holds_for_another_driver_and_a_refusal_never_reaches_it(stage):
    core, device, clock = stage
    before = dict(device.outputs)
    writes = sum(1 for entry in core.driver.log if entry.text.startswith("set"))
    for call, code in [
        (lambda: core.move({"x": 101.0}), "travel_limit"),
        (lambda: core.move({"x": 25.0}, relative=True), "step_limit"),
        (lambda: core.set_voltages({"x": 125.0}), "voltage_limit"),
        (lambda: core.move({"z": 1.0}), "bad_axis"),
    ]:
        with pytest.raises(Refused) as refused:
            call()
        assert refused.value.code == code
    assert device.outputs == before
    assert sum(1 for entry in core.driver.log if entry.text.startswith("set")) == writes
    # The watchdog, the owner and the stop work the same.
    core.arm(0.5, "run-1")
    with pytest.raises(Refused) as refused:
        core.move({"x": 0.5}, relative=True, owner="someone else")
    assert refused.value.code == "owned"
    clock.now += 1.0
    core.poll()
    assert core.state == "held"
    core.stop("operator")
    assert device.halts == 1  # the driver is told to halt motion in progress
    with pytest.raises(Refused) as refused:
        core.move({"x": 0.5}, relative=True)
    assert refused.value.code == "stopped"


def test_a_knob_turned_on_another_driver_stops_the_stage(stage):
    core, device, clock = stage
    device.outputs[0] += 3.0  # nobody commanded it
    clock.now += 5.0
    core.poll()
    assert core.state == "stopped" and "without a command from semservo" in core.state_reason


def test_a_pulled_cable_on_another_driver_is_link_lost_then_reconnects(stage):
    core, device, clock = stage
    device.plugged = False
    with pytest.raises(Refused) as refused:
        core.move({"x": 0.5}, relative=True)
    assert refused.value.code == "link_lost" and core.link == "lost"
    device.plugged = True
    clock.now += 10.0
    core.poll()
    assert core.link == "connected" and core.counters["reconnects"] == 1


def test_scan_settings_and_focus_reach_an_adapter_that_can_and_are_refused_by_one_that_cannot(tmp_path):
    from services.imageserver.sources import ReplaySource, set_scan
    from semservo.imagefiles import write_image

    source = adapter_source(ADAPTER, {"rows": 32, "cols": 32}, fps=100)
    try:
        assert set_scan(source, dwell_ns=500.0, working_distance_mm=3.5) == {"dwell_ns": 500.0,
                                                                           "working_distance_mm": 3.5}
        image = next_image(source)
        while image.dwell_ns != 500.0:  # a frame scanned before the change may still be waiting
            image = next_image(source)
        assert image.working_distance_mm == 3.5
        with pytest.raises(NotSupported, match="one magnification"):
            set_scan(source, magnification=2000.0)
        with pytest.raises(ValueError, match="outside"):
            set_scan(source, dwell_ns=1e9)
    finally:
        source.close()
    write_image(tmp_path / "a.png", np.zeros((32, 32), np.uint8))
    with pytest.raises(NotSupported, match="the replay source cannot set the focus"):
        set_scan(ReplaySource(tmp_path), working_distance_mm=3.0)
