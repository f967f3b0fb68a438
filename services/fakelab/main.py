"""Fake lab process: one simulated world, the NV 40/3 emulator on a pseudo-terminal and
TCP, a scan socket for the image server's ``sim`` source, the control socket (health,
true pose, rotation stage, presets) and, with ``save_frames_dir``, the SEM saving every
frame to a folder as a vendor's software does (for the ``watch`` source). With
``--sample-image FILE`` (``SEMSERVO_FAKELAB__SAMPLE_IMAGE``) a real SEM picture is the
sample, under the preset's optics (:mod:`semservo.simulation.sample_image`).

Run it with ``semservo fakelab`` (prints where the serial device is) or
``semservo service fakelab``; settings ``SEMSERVO_FAKELAB__*``.
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time

import pydantic
import zmq

from semservo.config import Settings, connect
from semservo.logs import configure
from semservo.messages import Reply, ScanRequest
from semservo.service import ServiceRuntime
from semservo.simulation import sample_image
from semservo.simulation.world import PRESETS, World
from semservo.wire import encode_frame, frame_header
from services.fakelab.acquisition import FolderWriter
from services.fakelab.commands import FakeLab, handlers
from services.fakelab.emulator import ChannelState, NV403Emulator
from services.fakelab.scan import scan_settings
from services.fakelab.serial_links import PseudoTerminalLink, TcpLink

log = logging.getLogger("fakelab")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="semservo fakelab",
        description="Run the simulated lab: a simulated SEM and an emulated NV 40/3 piezo amplifier "
                    "(serial protocol on a pseudo-terminal and on TCP) sharing one world.",
    )
    parser.add_argument("--preset", choices=sorted(PRESETS), help="experimental condition (default: settings)")
    parser.add_argument("--speedup", type=float, help="simulated time runs this many times faster")
    parser.add_argument("--no-pty", action="store_true", help="no pseudo-terminal (TCP only)")
    sample_image.add_arguments(parser)
    return parser


class ScanServer:
    """Serves frames to the image server in a thread of its own (a scan takes a frame
    time, which must not hold up the control socket)."""

    def __init__(self, world: World, endpoint: str, context: zmq.Context, max_message_bytes: int, counters):
        self.world = world
        self.socket = context.socket(zmq.REP)
        self.socket.setsockopt(zmq.LINGER, 0)
        self.socket.setsockopt(zmq.MAXMSGSIZE, max_message_bytes)
        self.socket.bind(endpoint)
        self.counters = counters
        self.sequence = 0
        self.last_error: str | None = None
        self.failed_in_a_row = 0
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, name="scan", daemon=True)

    def start(self) -> "ScanServer":
        self.thread.start()
        return self

    def _serve(self) -> None:
        while not self._stop.is_set():
            if not self.socket.poll(100):
                continue
            parts = self.socket.recv_multipart()
            try:
                request = ScanRequest.model_validate_json(parts[0]) if len(parts) == 1 else None
                if request is None:
                    raise ValueError(f"a scan request is one JSON part, got {len(parts)}")
                settings = scan_settings(self.world, request)
            except (pydantic.ValidationError, ValueError) as error:
                self.counters["scans_refused"] += 1
                self.last_error = f"scan refused: {error}"
                self.socket.send(Reply.failure("bad_request", str(error)).model_dump_json().encode())
                continue
            try:
                scan_started_at_ns = time.time_ns()
                pixels, start, end = self.world.scan(settings)
                # When the scan ended (the header's acquired_at_ns), not when the simulator
                # had drawn it: a real scan generator has no render time, and a frame's rows
                # are timed from its start and end (a partial frame after a move).
                acquired_at_ns = scan_started_at_ns + round((end - start) / self.world.speedup * 1e9)
            except Exception as error:  # noqa: BLE001 - the SEM must keep scanning, and say why one failed
                log.exception("a scan failed")
                self.counters["scans_failed"] += 1
                self.failed_in_a_row += 1
                self.last_error = f"scan failed: {type(error).__name__}: {error}"
                self.socket.send(Reply.failure("scan_failed", self.last_error).model_dump_json().encode())
                continue
            self.failed_in_a_row = 0
            header = frame_header(
                pixels, seq=self.sequence, acquired_at_ns=acquired_at_ns, pixel_size_nm=settings.pixel_um * 1000,
                magnification=settings.magnification, dwell_ns=settings.dwell_ns, source="fakelab",
                label=f"{self.world.preset.name} t={(start + end) / 2:.4f}s",
                scan_started_at_ns=scan_started_at_ns, source_interval_s=(start, end),
            )
            self.sequence += 1
            self.counters["frames_scanned"] += 1
            self.socket.send_multipart(encode_frame(header, pixels), copy=False)

    @property
    def healthy(self) -> bool:
        """Scanning: the thread lives and the last scan did not fail."""
        return self.thread.is_alive() and self.failed_in_a_row == 0

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=5)
        self.socket.close(linger=0)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # The sample-image options are settings (SEMSERVO_FAKELAB__SAMPLE_*): one validation.
    os.environ.update(sample_image.environment_from_arguments(args))
    try:
        settings = Settings()
    except pydantic.ValidationError as error:
        raise SystemExit(f"fakelab: bad settings: {error}") from None
    configure(settings.log_level)
    config = settings.fakelab
    preset_name = args.preset or config.preset
    if preset_name not in PRESETS:
        raise SystemExit(f"unknown preset {preset_name!r}; presets: {', '.join(sorted(PRESETS))}")
    try:
        sample = sample_image.from_settings(config)
        world = World(PRESETS[preset_name], speedup=args.speedup or config.speedup, seed=config.seed,
                      sample_image=sample)
    except sample_image.SampleImageError as error:
        raise SystemExit(f"fakelab: sample image refused: {error}") from None
    if sample is not None:
        description = sample.describe()
        log.info("sample: the picture %s, %d x %d px at %.4g nm/px (%s), %s edges, %s; noise %.4f -> %.4f (yield); "
                 "magnifications x%.4g..x%.4g", sample.name, sample.shape[1], sample.shape[0], sample.pixel_um * 1000,
                 sample.pixel_size_from, sample.edges,
                 f"heights 0..{sample.height_range_um:g} um" if sample.height_um is not None else "flat",
                 sample.noise_before, sample.noise_after, *description["magnification_range"])

    channels = {channel: ChannelState(knob_voltage=world.voltage(channel)) for channel in (0, 1, 2)}

    def make_emulator() -> NV403Emulator:
        return NV403Emulator(world, channels=channels)

    plugged = threading.Event()
    plugged.set()
    pty = None if args.no_pty else PseudoTerminalLink(make_emulator, plugged).start()
    tcp = TcpLink(make_emulator, config.serial_bind_host or settings.bind_host, config.serial_tcp_port, plugged).start()
    runtime = ServiceRuntime("fakelab", settings, settings.bind(config.control_port))
    scanner = ScanServer(world, settings.bind(config.scan_port), runtime.context, settings.max_message_bytes,
                         runtime.counters).start()
    saver = None
    if config.save_frames_dir is not None:  # the SEM's software saving to a folder, for the watch source
        saver = FolderWriter(world, config.save_frames_dir, chunks=config.save_chunks,
                             chunk_pause_s=config.save_chunk_pause_s, interval_s=config.save_interval_s,
                             counters=runtime.counters, keep=config.save_keep).start()
    runtime.report_errors_from(lambda: scanner.last_error or (saver and saver.last_error))
    # Said plainly on stdout: this is what a user plugs a stage service or a script into.
    if pty is not None:
        print(f"NV 40/3 serial port (pseudo-terminal): {pty.path}", flush=True)
    print(f"NV 40/3 serial port (TCP, pyserial URL): {tcp.url.replace(settings.bind_host, config.host)}", flush=True)
    log.info("SEM scans on %s, preset %s (%s), speed-up x%g", connect(config.host, config.scan_port),
             preset_name, world.preset.description, world.speedup)

    lab = FakeLab(world, plugged, lambda: {"serial_pty": pty.path if pty else None,
                                           "serial_tcp": tcp.url.replace(settings.bind_host, config.host),
                                           "scan_endpoint": connect(config.host, config.scan_port)})
    handlers.bind(runtime.control, lab)
    runtime.details = lambda: {"preset": world.preset.name, "world_id": world.id, "sample": world.preset.scene,
                               "serial_pty": pty.path if pty else None, "serial_tcp": tcp.url, "frames": world.frames,
                               "scanning": scanner.healthy}

    def step() -> float:
        # Health says so when the SEM cannot scan (a dead scan thread, failing scans).
        runtime.state = "running" if scanner.healthy else "degraded"
        return 0.5

    try:
        return runtime.run(step)
    finally:
        scanner.stop()
        if saver is not None:
            saver.stop()
        tcp.stop()
        if pty is not None:
            pty.stop()
        runtime.context.destroy(linger=0)  # closes what is still open: term() would wait on it


if __name__ == "__main__":
    raise SystemExit(main())
