"""Image server process: source -> core -> PUB socket; the commands (declared in
:mod:`semservo.protocol.imageserver`, answered by :mod:`services.imageserver.commands`)
on the control socket.

Run it with ``semservo service imageserver [options]``; options override the
``SEMSERVO_IMAGESERVER__*`` settings. Sources: ``sim`` (default; the fake lab's SEM),
``replay`` (a folder of frames; implied by ``--replay-dir``), ``watch`` (the folder an
SEM saves into; implied by ``--watch-dir``) and ``adapter`` (a lab's own class).

The loop sleeps until there is work: a command, the next frame due (replay), or a
source that says it has a frame (the simulated SEM's and an adapter's acquisition
threads, a watched folder's events) through a pipe the poller watches.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import time
from pathlib import Path

from semservo.config import Settings, connect
from semservo.logs import configure
from semservo.messages import ScanRequest
from semservo.service import ServiceRuntime
from semservo.transport import FramePublisher

from services.imageserver.commands import ImageServer, handlers
from services.imageserver.core import FreezeWatch, ImageServerCore
from services.imageserver.sources import BackgroundAcquisition, ReplaySource, SimSource, SourceUnavailable, adapter_source
from services.imageserver.watch import WatchSource

log = logging.getLogger("imageserver")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="semservo service imageserver",
        description="Publish SEM frames over ZeroMQ PUB/SUB from a source: the fake lab's simulated SEM "
                    "(sim), a replayed folder of PNG/TIFF frames (replay), a folder the SEM's software saves "
                    "frames into (watch), or a lab's adapter to its microscope's API (adapter).",
    )
    parser.add_argument("--source", choices=["sim", "replay", "watch", "adapter"],
                        help="frame source (default: settings; --replay-dir implies replay, --watch-dir watch, "
                             "--adapter adapter)")
    parser.add_argument("--replay-dir", type=Path, help="folder of PNG/TIFF frames, replayed in name order")
    parser.add_argument("--watch-dir", type=Path, help="folder the SEM's software saves frames into: each new "
                                                       "frame is published once, when its file is complete")
    parser.add_argument("--adapter", help="a lab's image source: entry point name or package.module:ClassName")
    parser.add_argument("--data-bar", help="rows of data bar to crop from files: auto (default) or a number")
    parser.add_argument("--glob", help="replay only files matching this pattern, e.g. 'frame*'")
    parser.add_argument("--fps", type=float, help="frames per second")
    loop = parser.add_mutually_exclusive_group()
    loop.add_argument("--loop", dest="loop", action="store_true", default=None, help="replay again at the end (default)")
    loop.add_argument("--once", dest="loop", action="store_false", help="replay the folder once, then idle")
    parser.add_argument("--magnification", type=float, help="magnification G, overriding the files")
    parser.add_argument("--pixel-size-nm", type=float, help="pixel size on the sample, overriding the files; "
                                                            "with only --magnification, P = D / G (eq. 43)")
    parser.add_argument("--dwell-ns", type=float, help="dwell time per pixel, overriding the files")
    return parser


def _data_bar(value) -> int | str:
    if value in (None, "auto") or isinstance(value, int):
        return "auto" if value is None else value
    try:
        rows = int(value)
    except ValueError:
        raise SystemExit(f"--data-bar must be auto or a number of rows, not {value!r}") from None
    if rows < 0:
        raise SystemExit(f"--data-bar must be auto or a number of rows >= 0, not {rows}")
    return rows


#: The watch source publishes every complete file as it comes: the pacer only caps the rate.
WATCH_MAX_FPS = 1000.0


def source_name(settings: Settings, args: argparse.Namespace) -> str:
    return args.source or ("replay" if args.replay_dir else "watch" if args.watch_dir
                           else "adapter" if args.adapter else settings.imageserver.source)


class Wakeup:
    """A pipe the poller watches: a source's threads write a byte when a frame (or an
    error) is ready, and the loop wakes at once instead of polling."""

    def __init__(self):
        self.read_fd, self.write_fd = os.pipe()
        os.set_blocking(self.read_fd, False)
        os.set_blocking(self.write_fd, False)

    def notify(self) -> None:
        # Full (a wake-up is pending anyway), or closed at exit: nothing to wake.
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self.write_fd, b"!")

    def drain(self) -> None:
        with contextlib.suppress(BlockingIOError):  # empty: every wake-up read
            while os.read(self.read_fd, 4096):
                continue

    def close(self) -> None:
        for fd in (self.read_fd, self.write_fd):
            os.close(fd)


def make_source(settings: Settings, args: argparse.Namespace, notify=None):
    """The source the settings and options name, ready to acquire; ``notify`` is told
    when it has a frame."""
    config = settings.imageserver
    source = source_name(settings, args)
    fps = args.fps or config.fps
    # From files: the user's options override them; the settings fill what they do not say.
    overrides = {"magnification": args.magnification, "pixel_size_nm": args.pixel_size_nm, "dwell_ns": args.dwell_ns}
    fallbacks = {"magnification": config.magnification, "pixel_size_nm": config.pixel_size_nm,
                 "dwell_ns": config.dwell_ns}
    data_bar = _data_bar(args.data_bar if args.data_bar is not None else config.data_bar)
    if source == "sim":
        request = ScanRequest(dwell_ns=args.dwell_ns or config.scan_dwell_ns,
                              magnification=args.magnification or config.scan_magnification,
                              working_distance_um=config.scan_working_distance_um,
                              aperture_um=config.scan_aperture_um,
                              brightness=config.scan_brightness, contrast=config.scan_contrast,
                              bit_depth=config.scan_bit_depth)
        # A scan takes a frame time: acquire in the background so health stays responsive.
        return BackgroundAcquisition(
            SimSource(connect(settings.fakelab.host, settings.fakelab.scan_port), request,
                      timeout_s=config.scan_timeout_s, max_message_bytes=settings.max_message_bytes),
            fps=fps, notify=notify,
        )
    if source == "watch":
        folder = args.watch_dir or config.watch_dir
        if folder is None:
            raise SystemExit("the watch source needs a folder: --watch-dir or SEMSERVO_IMAGESERVER__WATCH_DIR")
        return WatchSource(folder, pattern=args.glob or config.watch_glob, existing=config.watch_existing,
                           settle_s=config.watch_settle_s, give_up_s=config.watch_give_up_s,
                           polling=config.watch_polling, overrides=overrides, fallbacks=fallbacks, data_bar=data_bar,
                           notify=notify)
    if source == "adapter":
        spec = args.adapter or config.adapter
        if not spec:
            raise SystemExit("the adapter source needs a class: --adapter or SEMSERVO_IMAGESERVER__ADAPTER "
                             "(an entry point of semservo.image_sources or package.module:ClassName)")
        return adapter_source(spec, dict(config.adapter_options), fps, notify=notify)
    return ReplaySource(
        args.replay_dir or config.replay_dir,
        pattern=args.glob or config.replay_glob,
        loop=config.loop if args.loop is None else args.loop,
        overrides=overrides, fallbacks=fallbacks, data_bar=data_bar,
    )


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    settings = Settings()
    configure(settings.log_level)
    config = settings.imageserver

    runtime = ServiceRuntime("imageserver", settings, settings.bind(config.control_port))
    wakeup = Wakeup()
    try:
        source = make_source(settings, args, notify=wakeup.notify)
    except (OSError, ValueError, TypeError) as error:  # a missing folder, a bad adapter: say which, and stop
        log.error("cannot start the %s source: %s", source_name(settings, args), error)
        return 2
    # A watched folder publishes every complete file as it comes: the pacer only caps the rate.
    fps = WATCH_MAX_FPS if not getattr(source, "paced", True) else args.fps or config.fps
    core = ImageServerCore(source, fps=fps)
    publisher = FramePublisher(settings.bind(config.frames_port), context=runtime.context)
    # A cap: a source slower than it (a simulated or real scan of seconds) sets the pace.
    log.info("publishing %s on %s, at most %.1f fps", source.describe(), publisher.endpoint, core.pacer.fps)
    server = ImageServer(core, frames_endpoint=connect(config.host, config.frames_port),
                         published=lambda: publisher.sent)
    handlers.bind(runtime.control, server)
    runtime.details = lambda: {"source": source.name, "fps": core.pacer.fps, "next_seq": core.seq,
                               **({"watch": source.describe()} if not getattr(source, "paced", True) else {})}

    retry_at = 0.0
    freeze = FreezeWatch()
    started = time.monotonic()

    def frozen() -> bool:
        """A source that stopped delivering (a hung SEM, a dead simulator) is degraded.
        A watched folder is not: an SEM that saves nothing for a while is simply not
        scanning (a run waiting for frames fails on its own estimate timeout, saying so)."""
        if getattr(source, "idle_is_normal", False):
            return False
        silent = None if core.exhausted else freeze.silent_for(time.monotonic(), started)
        if silent is not None and runtime.state != "degraded":
            runtime.error(f"the frame source is frozen: no frame for {silent:.1f} s ({source.name})")
        return silent is not None

    def step() -> float | None:
        nonlocal retry_at
        if time.monotonic() < retry_at:
            runtime.state = "degraded"
            return min(retry_at - time.monotonic(), 0.5)
        try:
            due = core.next_frame()
        except SourceUnavailable as error:
            # Say so in health and try again shortly; never crash on a missing device.
            runtime.error(str(error))
            runtime.state = "degraded"
            retry_at = time.monotonic() + 1.0
            return 1.0
        if due is not None:
            freeze.frame(time.monotonic())
        if runtime.state in ("running", "degraded"):
            runtime.state = "degraded" if frozen() else "running"
        if due is not None:
            seq, image = due
            publisher.publish(
                image.pixels,
                seq=seq,
                acquired_at_ns=image.acquired_at_ns,
                source=source.name,
                label=image.label,
                scan_started_at_ns=image.scan_started_at_ns,
                source_interval_s=image.source_interval_s,
                **image.acquisition(),
            )
            runtime.counters["frames_published"] += 1
        for name, value in getattr(source, "counters", {}).items():  # a watched folder's files_* counts
            runtime.counters[name] = value
        if core.exhausted and runtime.state == "running":
            runtime.state = "finished"
            log.info("replay finished after %d frames", core.seq)
        wait = core.seconds_until_due()
        return None if wait is None else min(wait, 0.5)

    def on_wakeup() -> None:
        wakeup.drain()  # the step that follows every poll publishes what is ready

    runtime.add_reader(wakeup.read_fd, on_wakeup)
    try:
        return runtime.run(step)
    finally:
        server.close()
        if hasattr(source, "close"):
            source.close()
        publisher.close()
        wakeup.close()
        runtime.context.destroy(linger=0)  # closes what is still open: term() would wait on it


if __name__ == "__main__":
    raise SystemExit(main())
