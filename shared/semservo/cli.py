"""The ``semservo`` command.

    semservo up         start the whole system and show it working (Ctrl-C stops it)
    semservo service    run one service in the foreground (what ``up`` and containers run)
    semservo frames     watch a frame stream
    semservo health     ask every service how it is
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import time
from pathlib import Path

from semservo import __version__
from semservo.config import Settings, connect
from semservo.launcher import SERVICES, LaunchError, Launcher, spec
from semservo.monitor import FrameStats
from semservo.transport import ControlClient, FrameSubscriber, ServiceUnavailable


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def _replay_environment(args: argparse.Namespace) -> None:
    """Turn the replay options of ``up`` into settings every child inherits."""
    overrides = {
        "SEMSERVO_IMAGESERVER__REPLAY_DIR": args.replay_dir and str(Path(args.replay_dir).resolve()),
        "SEMSERVO_IMAGESERVER__REPLAY_GLOB": args.glob,
        "SEMSERVO_IMAGESERVER__FPS": args.fps and str(args.fps),
        "SEMSERVO_IMAGESERVER__LOOP": None if args.loop is None else str(args.loop).lower(),
        "SEMSERVO_IMAGESERVER__MAGNIFICATION": args.magnification and str(args.magnification),
    }
    os.environ.update({key: value for key, value in overrides.items() if value})


def command_up(args: argparse.Namespace) -> int:
    _replay_environment(args)
    settings = Settings()
    launcher = Launcher(settings, restart=args.restart)
    signal.signal(signal.SIGTERM, _raise_interrupt)
    launcher.say(f"semservo {__version__}: starting {', '.join(s.name for s in SERVICES)}")
    try:
        launcher.start(timeout_s=args.timeout)
    except LaunchError as error:
        launcher.say(f"failed to start: {error}")
        return 1
    except KeyboardInterrupt:
        return 130
    launcher.say("all services healthy:\n" + launcher.table())

    frames_endpoint = connect(settings.imageserver.host, settings.imageserver.frames_port)
    subscriber = FrameSubscriber(frames_endpoint, max_message_bytes=settings.max_message_bytes, latest_only=False)
    stats = FrameStats()
    code = 0
    started = time.monotonic()
    last_report = started
    if args.check:
        launcher.say(f"checking: waiting for {args.frames} frames on {frames_endpoint}")
    else:
        launcher.say(f"watching frames on {frames_endpoint}; Ctrl-C stops everything")
    try:
        while True:
            frame = subscriber.receive(timeout_s=0.2)
            if frame is not None:
                stats.add(frame)
            now = time.monotonic()
            down = launcher.supervise()
            if args.check:
                if stats.frames >= args.frames:
                    launcher.say("frames flowing: " + stats.summary(subscriber.counters))
                    launcher.say(f"check passed: {stats.frames} valid frames received through ZeroMQ")
                    break
                if down or now - started > args.timeout:
                    reason = f"{', '.join(down)} down" if down else f"timed out after {args.timeout:.0f} s"
                    launcher.say(f"check FAILED ({reason}): " + stats.summary(subscriber.counters))
                    code = 1
                    break
            elif now - last_report >= args.status_every:
                launcher.say("frames flowing: " + stats.summary(subscriber.counters) if stats.frames else "waiting for frames")
                last_report = now
    except KeyboardInterrupt:
        launcher.say("stopping")
    finally:
        subscriber.close()
        launcher.stop()
    return code


def command_service(args: argparse.Namespace) -> int:
    module = importlib.import_module(spec(args.name).module)
    return module.main(args.service_args)


def command_frames(args: argparse.Namespace) -> int:
    settings = Settings()
    endpoint = args.endpoint or connect(settings.imageserver.host, settings.imageserver.frames_port)
    subscriber = FrameSubscriber(endpoint, max_message_bytes=settings.max_message_bytes, latest_only=False)
    stats = FrameStats()
    deadline = time.monotonic() + args.timeout
    try:
        while stats.frames < args.count and time.monotonic() < deadline:
            frame = subscriber.receive(timeout_s=0.2)
            if frame is None:
                continue
            stats.add(frame)
            header = frame.header
            print(f"seq {header.seq:6d}  {header.shape[1]}x{header.shape[0]} {header.dtype}  "
                  f"{header.source}{' ' + header.label if header.label else ''}  "
                  f"mean {frame.pixels.mean():7.2f}")
    except KeyboardInterrupt:
        pass
    finally:
        subscriber.close()
    print(stats.summary(subscriber.counters))
    return 0 if stats.frames else 1


def command_health(args: argparse.Namespace) -> int:
    settings = Settings()
    names = args.names or [service.name for service in SERVICES]
    code = 0
    for name in names:
        client = ControlClient(spec(name).control(settings), timeout_s=settings.request_timeout_s, retries=1)
        try:
            health = client.request("health")
            counters = ", ".join(f"{k}={v}" for k, v in sorted(health["counters"].items()))
            print(f"{name:<12} {health['state']:<9} pid {health['pid']:<7} up {health['uptime_s']:.0f} s  "
                  f"{counters}{'  last error: ' + health['last_error'] if health['last_error'] else ''}")
        except ServiceUnavailable:
            print(f"{name:<12} DOWN      (no answer on {client.endpoint})")
            code = 1
        finally:
            client.close()
    return code


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="semservo",
        description="Image-guided nanopositioning for SEM (Marturi et al.): services, launcher and tools.",
    )
    parser.add_argument("--version", action="version", version=f"semservo {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    up = commands.add_parser("up", help="start every service and show frames flowing",
                             description="Start every service as a child process, wait until each is healthy, "
                                         "print what runs where, stream their logs, and stop them all on Ctrl-C.")
    up.add_argument("--check", action="store_true", help="exit after showing that frames flow (for scripts)")
    up.add_argument("--frames", type=int, default=20, help="frames --check waits for (default 20)")
    up.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for health and for --check")
    up.add_argument("--restart", action="store_true", help="restart a service that dies (with back-off)")
    up.add_argument("--status-every", type=float, default=5.0, help="seconds between status lines")
    up.add_argument("--replay-dir", help="folder of frames to replay (default: the 2013 recording)")
    up.add_argument("--glob", help="replay only files matching this pattern, e.g. 'frame*'")
    up.add_argument("--fps", type=float, help="replay frame rate")
    loop = up.add_mutually_exclusive_group()
    loop.add_argument("--loop", dest="loop", action="store_true", default=None, help="replay in a loop (default)")
    loop.add_argument("--once", dest="loop", action="store_false", help="replay once")
    up.add_argument("--magnification", type=float, help="magnification of the replayed frames")
    up.set_defaults(handler=command_up)

    service = commands.add_parser("service", help="run one service in the foreground",
                                  description="Run one service; options after its name go to the service "
                                              "(see 'semservo service NAME --help').")
    service.add_argument("name", choices=[s.name for s in SERVICES])
    service.add_argument("service_args", nargs=argparse.REMAINDER, help="options for the service")
    service.set_defaults(handler=command_service)

    frames = commands.add_parser("frames", help="watch a frame stream and print each header")
    frames.add_argument("--count", type=int, default=10, help="frames to print (default 10)")
    frames.add_argument("--timeout", type=float, default=30.0, help="give up after this many seconds")
    frames.add_argument("--endpoint", help="frames address (default: the image server's)")
    frames.set_defaults(handler=command_frames)

    health = commands.add_parser("health", help="ask services for their health")
    health.add_argument("names", nargs="*", help="services (default: all)")
    health.set_defaults(handler=command_health)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.handler(args)


if __name__ == "__main__":
    sys.exit(main())
