"""The NV 40/3 driver against the emulated amplifier over a real pseudo-terminal and TCP."""

from __future__ import annotations

import os
import tty

import pytest

from semservo import nv40
from semservo.nv40_driver import LinkError, NV403Driver
from semservo.simulation.world import World
from services.fakelab.emulator import ChannelState, NV403Emulator
from services.fakelab.serial_links import PseudoTerminalLink, TcpLink

pytestmark = pytest.mark.integration


@pytest.fixture
def world():
    return World(speedup=100.0)


@pytest.fixture
def links(world):
    channels = {channel: ChannelState(knob_voltage=world.voltage(channel)) for channel in nv40.CHANNELS}

    def make_emulator():
        return NV403Emulator(world, channels=channels)

    pty = PseudoTerminalLink(make_emulator).start()
    tcp = TcpLink(make_emulator, "127.0.0.1", 0).start()
    yield pty, tcp
    tcp.stop()
    pty.stop()


@pytest.mark.parametrize("transport", ["pty", "tcp"])
def test_identify_remote_set_and_read_back(links, world, transport):
    pty, tcp = links
    driver = NV403Driver.open(pty.path if transport == "pty" else tcp.url)
    try:
        identity = driver.identify()
        assert identity["prompt"] == "NV403CLE>" and identity["firmware"][0].startswith("NV40/3")
        assert driver.voltage_limits() == (-20.0, 130.0)
        assert not driver.is_remote(0)
        driver.set_remote(0)
        assert driver.is_remote(0)
        assert driver.set_voltage(0, 45.25) == 45.25
        assert world.voltage(0) == 45.25
        assert driver.read_voltages() == (45.25, 38.0, 38.0)
        for channel in (1, 2):
            driver.set_remote(channel)
        assert driver.set_voltages((40.0, 41.0, 42.0)) == (40.0, 41.0, 42.0)
        driver.release()
        assert not any(driver.is_remote(channel) for channel in nv40.CHANNELS)
        assert driver.set_voltage(0, 60.0) == 40.0  # ignored under front-panel control
    finally:
        driver.close()
    sent = [entry.text for entry in driver.log if entry.direction == "sent"]
    assert "set,0,45.250" in sent and all(entry.time_ns > 0 for entry in driver.log)


def test_error_replies_raise_protocol_errors(links):
    pty, _ = links
    driver = NV403Driver.open(pty.path)
    try:
        driver.set_remote(0)
        with pytest.raises(nv40.ProtocolError) as caught:
            driver.set_voltage(0, 500.0)
        assert caught.value.code == nv40.ERROR_OUT_OF_RANGE
        with pytest.raises(nv40.ProtocolError) as caught:
            driver.read_voltage(7)
        assert caught.value.code == nv40.ERROR_UNKNOWN_CHANNEL
        assert driver.read_voltage(0) == 38.0  # nothing moved, the link still works
    finally:
        driver.close()


def test_a_silent_port_is_a_link_error_not_a_hang():
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        driver = NV403Driver.open(os.ttyname(slave), reply_timeout_s=0.2)
        with pytest.raises(LinkError, match="no prompt"):
            driver.identify()
        with pytest.raises(LinkError, match="no reply"):
            driver.read_voltage(0)
        driver.close()
    finally:
        os.close(master)
        os.close(slave)


def test_a_vanished_port_is_a_link_error(links):
    _, tcp = links
    driver = NV403Driver.open(tcp.url, reply_timeout_s=0.3)
    assert driver.read_voltage(1) == 38.0
    tcp.stop()  # the amplifier's end goes away
    with pytest.raises(LinkError):
        for _ in range(5):  # the closed connection is noticed on the next exchanges
            driver.read_voltage(1)
    driver.close()
    with pytest.raises(LinkError, match="cannot open"):
        NV403Driver.open("/dev/does-not-exist")
