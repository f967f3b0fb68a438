"""The ``semservo`` command.

    semservo up         start the whole system and show it working (Ctrl-C stops it)
    semservo service    run one service in the foreground (what ``up`` and containers run)
    semservo fakelab    run the simulated lab alone (prints the emulated serial port)
    semservo frames     watch a frame stream
    semservo health     ask every service how it is
    semservo estimate   measure motion between image files (no services needed)
    semservo teach      teach the running estimator a reference
    semservo motion     watch the estimator's motion stream
    semservo calibrate  sweep a stage axis, measure it in the images, fit its model
    semservo demo       teach, displace the stage, position back, print the result
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import math
import os
import signal
import sys
import time
from pathlib import Path
from typing import NoReturn

import numpy as np
import pydantic
import zmq

from semservo import __version__, security
from semservo.config import Settings, connect, unrecognised_settings
from semservo.launcher import SERVICES, Launcher, LaunchError, spec, stage_rate_for
from semservo.messages import MOTION_TOPIC, MotionEstimate
from semservo.monitor import FrameStats, acquisition_text
from semservo.protocol import ServicePort
from semservo.simulation import sample_image
from semservo.simulation.world import PRESETS
from semservo.transport import CommandError, ControlClient, FrameSubscriber, MessageSubscriber, ServiceUnavailable
from semservo.wording import taught_sweeps, tilt_teach_progress


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def _source_environment(args: argparse.Namespace) -> None:
    """Turn the source options of ``up`` into settings every child inherits."""
    overrides = {
        "SEMSERVO_IMAGESERVER__SOURCE": args.source or (args.replay_dir and "replay") or (args.watch_dir and "watch"),
        "SEMSERVO_IMAGESERVER__REPLAY_DIR": args.replay_dir and str(Path(args.replay_dir).resolve()),
        "SEMSERVO_IMAGESERVER__WATCH_DIR": args.watch_dir and str(Path(args.watch_dir).resolve()),
        "SEMSERVO_FAKELAB__SAVE_FRAMES_DIR": args.watch_dir and args.sim_saves_frames
                                             and str(Path(args.watch_dir).resolve()),
        "SEMSERVO_FAKELAB__PRESET": args.preset,
        "SEMSERVO_FAKELAB__SPEEDUP": _text(args.speedup),
        "SEMSERVO_IMAGESERVER__REPLAY_GLOB": args.glob if not args.watch_dir else None,
        "SEMSERVO_IMAGESERVER__WATCH_GLOB": args.glob if args.watch_dir else None,
        "SEMSERVO_IMAGESERVER__FPS": _text(args.fps),
        "SEMSERVO_IMAGESERVER__LOOP": None if args.loop is None else str(args.loop).lower(),
        "SEMSERVO_IMAGESERVER__MAGNIFICATION": _text(args.magnification),
    }
    os.environ.update({key: value for key, value in overrides.items() if value})
    os.environ.update(sample_image.environment_from_arguments(args))
    try:
        speedup = float(os.environ.get("SEMSERVO_FAKELAB__SPEEDUP") or 1.0)
    except ValueError:
        speedup = 1.0  # not a number: the settings refuse it by its own name
    # A rate only from a speed-up that can be one: a bad one is refused by its own name,
    # not as a stage rate the user never set.
    if (math.isfinite(speedup) and speedup > 0 and speedup != 1.0
            and "SEMSERVO_STAGE__MAX_RATE_V_PER_S" not in os.environ):
        os.environ["SEMSERVO_STAGE__MAX_RATE_V_PER_S"] = str(stage_rate_for(speedup))


def _text(value: float | None) -> str | None:
    """An option's value as a setting (None: not given; 0 is a value, not "unset")."""
    return None if value is None else str(value)


def settings_problems(error: pydantic.ValidationError) -> str:
    """Every problem of the settings, each by the environment variable that sets it
    (``SEMSERVO_FAKELAB__SPEEDUP: Input should be greater than 0``), not pydantic's dump."""
    problems = []
    for problem in error.errors():
        name = "SEMSERVO_" + "__".join(str(part) for part in problem.get("loc", ())).upper()
        given = problem.get("input")
        problems.append(f"{name}{f' = {given!r}' if isinstance(given, (str, int, float)) else ''}: {problem['msg']}")
    return "; ".join(problems)


def _warn_unused_sample_options(command: str, settings: Settings) -> None:
    """Say so when sample options will not be seen: without a sample image, a height
    without a height map, or a picture while the frames come from elsewhere."""
    fakelab, source = settings.fakelab, settings.imageserver.source
    if fakelab.sample_image is None:
        unused = [f"--{option.replace('_', '-')}" for option, setting in sample_image.OPTION_SETTINGS.items()
                  if option != "sample_image" and f"SEMSERVO_FAKELAB__{setting}" in os.environ]
        if unused:
            print(f"semservo {command}: {', '.join(unused)} {'has' if len(unused) == 1 else 'have'} no effect without "
                  "--sample-image", file=sys.stderr)
        return
    if fakelab.sample_height_um is not None and fakelab.sample_height_image is None:
        print(f"semservo {command}: --sample-height-um has no effect without --sample-height-image (the sample is "
              "flat)", file=sys.stderr)
    if source != "sim" and not (source == "watch" and fakelab.save_frames_dir is not None):
        print(f"semservo {command}: the sample image is the simulated SEM's sample, but the frames come from the "
              f"{source} source: they will not show it (it shows with --source sim, or the simulated SEM saving into "
              "the watched folder: --sim-saves-frames)", file=sys.stderr)


def _sample_image_environment(command: str) -> bool:
    """With a sample image set (options or settings): check it before anything starts,
    and set what follows from it (the estimator's depth of field for the tilts) where
    not set already. False, with the reason on stderr, when the picture is refused."""
    for problem in unrecognised_settings():
        print(f"semservo {command}: {problem}", file=sys.stderr)
    try:
        _warn_unused_sample_options(command, Settings())
        derived = sample_image.system_environment(Settings())
    except sample_image.SampleImageError as error:
        print(f"semservo {command}: sample image refused: {error}", file=sys.stderr)
        return False
    except pydantic.ValidationError as error:
        print(f"semservo {command}: settings refused: {settings_problems(error)}", file=sys.stderr)
        return False
    for key, value in derived.items():
        os.environ.setdefault(key, value)
    return True


def command_up(args: argparse.Namespace) -> int:
    if args.sim_saves_frames and not args.watch_dir:
        print("semservo up: --sim-saves-frames needs --watch-dir (the folder to save into)", file=sys.stderr)
        return 2
    if args.watch_dir:
        if args.sim_saves_frames:
            Path(args.watch_dir).mkdir(parents=True, exist_ok=True)
        elif not Path(args.watch_dir).is_dir():
            print(f"semservo up: no folder to watch at {args.watch_dir}", file=sys.stderr)
            return 2
    _source_environment(args)
    if not _sample_image_environment("up"):
        return 2
    settings = Settings()
    launcher = Launcher(settings, restart=args.restart)
    # Ctrl-C stops everything even when started from a shell that ignores SIGINT for
    # its background jobs (Python keeps an inherited "ignore").
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _raise_interrupt)
    code = 0
    try:
        launcher.say(f"semservo {__version__}: starting {', '.join(s.name for s in SERVICES)}")
        try:
            launcher.start(timeout_s=args.timeout)
        except LaunchError as error:
            launcher.say(f"failed to start: {error}")
            return 1
        launcher.say("all services healthy:\n" + launcher.table())
        code = _watch(settings, launcher, args)
    except KeyboardInterrupt:
        launcher.say("stopping")
    finally:
        # A second Ctrl-C must not cut the orderly stop short.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        launcher.stop()
    return code


def _watch(settings: Settings, launcher: Launcher, args: argparse.Namespace) -> int:
    """Show frames flowing (and with --check, verify the stack); returns the exit code."""
    frames_endpoint = connect(settings.imageserver.host, settings.imageserver.frames_port)
    subscriber = FrameSubscriber(frames_endpoint, max_message_bytes=settings.max_message_bytes, latest_only=False)
    stats = FrameStats()
    started = last_report = time.monotonic()
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
                    if any(s.name == "estimator" for s in SERVICES):
                        return _check_estimator(settings, launcher, args.timeout)
                    return 0
                if down or now - started > args.timeout:
                    reason = f"{', '.join(down)} down" if down else f"timed out after {args.timeout:.0f} s"
                    launcher.say(f"check FAILED ({reason}): " + stats.summary(subscriber.counters))
                    return 1
            elif now - last_report >= args.status_every:
                launcher.say("frames flowing: " + stats.summary(subscriber.counters) if stats.frames else "waiting for frames")
                last_report = now
    finally:
        subscriber.close()


def _check_estimator(settings: Settings, launcher: Launcher, timeout_s: float) -> int:
    """Teach the estimator the live frame and show motion estimates arriving."""
    control = ControlClient(connect(settings.estimator.host, settings.estimator.control_port),
                            timeout_s=max(settings.request_timeout_s, 10.0), retries=1)
    motion = MessageSubscriber(connect(settings.estimator.host, settings.estimator.motion_port),
                               MOTION_TOPIC, MotionEstimate)
    try:
        reference = control.request("teach")
        launcher.say(f"estimator taught the live frame {reference['frame_seq']} as reference {reference['id']}")
        estimates: list[MotionEstimate] = []
        deadline = time.monotonic() + timeout_s
        while len(estimates) < 5 and time.monotonic() < deadline:
            estimate = motion.receive(timeout_s=0.5)
            if estimate is not None and estimate.reference_id == reference["id"]:
                estimates.append(estimate)
                launcher.say(f"motion of frame {estimate.seq}: dx {estimate.dx_px:+8.3f} px  dy {estimate.dy_px:+8.3f} px  "
                             f"rotation {estimate.rotation_deg:+7.3f} deg  confidence {estimate.confidence:.2f}  "
                             f"SNR {estimate.snr_db:5.1f} dB  {estimate.estimation_ms:.1f} ms")
        if len(estimates) < 5:
            launcher.say("check FAILED: the estimator published no motion")
            return 1
        launcher.say(f"check passed: {len(estimates)} motion estimates against the taught reference")
        return 0
    except (ServiceUnavailable, CommandError) as error:
        launcher.say(f"check FAILED: estimator: {error}")
        return 1
    finally:
        control.close()
        motion.close()


#: ``semservo estimate --crop auto``: sizes this close (a data bar's rows) are cropped to the common region.
AUTO_CROP_FRACTION = 0.1


def _polygon(text: str) -> list[tuple[float, float]]:
    """A polygon option's corner points, 'X,Y X,Y ...' (pixels; at least three, finite)."""
    try:
        points = [tuple(float(value) for value in point.split(",")) for point in text.split()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"corner points are X,Y pairs of numbers, got {text!r}") from None
    if len(points) < 3 or any(len(point) != 2 or not all(math.isfinite(v) for v in point) for point in points):
        raise argparse.ArgumentTypeError(f"at least three corner points, each X,Y of finite numbers, got {text!r}")
    return points


def _count(text: str, most: int | None = None) -> int:
    """A positive count of things (at most ``most``)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1 or (most is not None and value > most):
        raise argparse.ArgumentTypeError(f"must be 1{f'..{most}' if most else ' or more'}, got {value}")
    return value


def _service_name(text: str) -> str:
    """A service's name, refused with the list of names otherwise."""
    names = [service.name for service in SERVICES]
    if text not in names:
        raise argparse.ArgumentTypeError(f"no service {text!r}; services: {', '.join(names)}")
    return text


def _teach_frames(text: str) -> int:
    """Live frames averaged into a reference: 1..16, as the estimator takes."""
    return _count(text, most=16)


def _number(low: float = -math.inf, high: float = math.inf, *, above: bool = False):
    """An option's type: a finite number from ``low`` (excluded when ``above``) to ``high``,
    so a bad value is refused before anything is taught, moved or started."""
    def number(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not math.isfinite(value) or value < low or (above and value == low) or value > high:
            if math.isfinite(low) and math.isfinite(high) and not above:
                bounds = f"from {low:g} to {high:g}"
            else:
                bounds = (f"over {low:g}" if above else f"at least {low:g}") if math.isfinite(low) else ""
                if math.isfinite(high):
                    bounds += (" and " if bounds else "") + f"at most {high:g}"
            raise argparse.ArgumentTypeError(f"must be a finite number{' ' + bounds if bounds else ''}, got {text}")
        return value
    number.__name__ = "number"  # argparse names the type in its messages
    return number


_positive = _number(0, above=True)
_finite = _number()


def command_estimate(args: argparse.Namespace) -> int:
    """Motion of each IMAGE against REFERENCE, one line (or JSON object) per image."""
    import json

    from semservo.estimation import MotionEstimator, as_image
    from semservo.imagefiles import ImageFileError, read_image

    def fail(message: str) -> None:
        print(f"semservo estimate: {message}", file=sys.stderr)

    try:
        reference, _ = read_image(args.reference)
    except (ImageFileError, FileNotFoundError) as error:
        fail(str(error))
        return 2
    readable, failures = [], 0
    for path in args.images:
        try:
            readable.append((path, as_image(read_image(path)[0], path)))
        except (ImageFileError, FileNotFoundError, ValueError) as error:
            readable.append((path, error))
    shapes = [reference.shape] + [pixels.shape for _, pixels in readable if not isinstance(pixels, Exception)]
    common = (min(shape[0] for shape in shapes), min(shape[1] for shape in shapes))
    if len(set(shapes)) > 1 and args.crop != "none":
        # A data bar cut from one file and not the other (the rows differ by a few), or
        # frames of slightly different scans: compare the region they share, said so.
        largest = max(max(shape[0] - common[0], shape[1] - common[1]) / min(shape) for shape in shapes)
        if args.crop == "common" or largest <= AUTO_CROP_FRACTION:
            fail(f"note: sizes differ ({', '.join(sorted({f'{c} x {r}' for r, c in shapes}))}): comparing the "
                 f"common {common[1]} x {common[0]} from the top left (--crop none refuses instead)")
            reference = reference[:common[0], :common[1]]
            readable = [(path, pixels if isinstance(pixels, Exception) else pixels[:common[0], :common[1]])
                        for path, pixels in readable]
        else:
            fail(f"sizes differ by more than {AUTO_CROP_FRACTION:.0%} ({', '.join(sorted({f'{c} x {r}' for r, c in shapes}))}): "
                 f"not the same scan? --crop common compares their common region anyway")
    mask = None
    if args.mask or args.polygon:
        # The reference file is the mask (or the image the polygon is drawn on); the
        # grey levels come from the first readable image, so polarity matches the scene.
        levels = next((pixels for _, pixels in readable if not isinstance(pixels, Exception)), None)
        if levels is None:
            fail("a mask reference needs at least one readable image for its grey levels")
            return 2
        if args.polygon:
            mask = args.polygon
        else:
            from semservo.estimation.masks import binary_region

            try:
                mask = binary_region(reference, f"{args.reference} (the mask)")
            except ValueError as error:
                fail(str(error))
                return 2
        reference = levels
    try:
        estimator = MotionEstimator(reference, rotation=not args.no_rotation, mask=mask, precision=args.precision,
                                    scan_averaged=args.scan_averaged)
    except ValueError as error:
        fail(f"{args.reference}: {error}")
        return 2
    for path, pixels in readable:
        if isinstance(pixels, Exception):
            fail(str(pixels))
            failures += 1
            continue
        if float(np.ptp(pixels)) == 0.0:  # as a flat reference is refused: nothing to register
            fail(f"{path}: the image is flat (every pixel {float(pixels.flat[0]):g}): nothing to register")
            failures += 1
            continue
        started = time.perf_counter()
        try:
            motion = estimator.estimate(pixels)
        except ValueError as error:
            fail(f"{path}: {error}")
            failures += 1
            continue
        elapsed_ms = (time.perf_counter() - started) * 1e3
        fields = {"image": str(path), **{k: v for k, v in motion.as_dict().items()
                                         if k in ("dx_px", "dy_px", "rotation_deg", "confidence", "snr_db")},
                  "elapsed_ms": elapsed_ms}
        if args.json:  # JSON has no infinity (a frame of pure noise has an SNR of -inf dB): null
            fields = {key: value if not isinstance(value, float) or math.isfinite(value) else None
                      for key, value in fields.items()}
            print(json.dumps(fields), flush=True)
        else:
            print(f"{path}  dx_px={motion.dx:+9.4f}  dy_px={motion.dy:+9.4f}  rotation_deg={motion.rotation_deg:+8.4f}  "
                  f"confidence={motion.confidence:.3f}  snr_db={motion.snr_db:5.1f}  elapsed_ms={elapsed_ms:6.2f}",
                  flush=True)
    return 1 if failures else 0


def _run_in_the_way(settings) -> str | None:
    """Why a teach now would break a run, in words, or None: the run the controller is
    servoing, or a controller that does not answer (then whether one servoes is unknown)."""
    from semservo.protocol import controller as controller_protocol

    controller = ServicePort(ControlClient(connect(settings.controller.host, settings.controller.control_port),
                                           timeout_s=max(settings.request_timeout_s, 2.0), retries=1))
    try:
        status = controller.call(controller_protocol.STATUS)
    except (ServiceUnavailable, CommandError) as error:
        return f"the controller does not answer ({error}), so whether a run servoes is not known"
    finally:
        controller.close()
    return f"run {status.run_id or '?'} is servoing" if status.state == "servoing" else None


def command_teach(args: argparse.Namespace) -> int:
    """Teach the running estimator: the one reference the gateway, the dashboard and every
    run use (whoever teaches it)."""
    import base64

    from semservo.protocol import estimator as estimator_protocol

    if args.image and not Path(args.image).is_file():
        what = "a folder, not an image file" if Path(args.image).is_dir() else "no such image file"
        print(f"semservo teach: {args.image}: {what}", file=sys.stderr)
        return 2
    settings = Settings()
    if not args.during_run:
        in_the_way = _run_in_the_way(settings)
        if in_the_way:
            remedy = ("is the system up? semservo up starts it" if in_the_way.startswith("the controller")
                      else "a new reference would fail it: stop it first (semservo stop, the dashboard's STOP or "
                           "POST /stop)")
            print(f"semservo teach: refused: {in_the_way}; {remedy}; or --during-run to teach anyway",
                  file=sys.stderr)
            return 1
    estimator = ServicePort(ControlClient(connect(settings.estimator.host, settings.estimator.control_port),
                                          timeout_s=max(settings.request_timeout_s, 10.0), retries=1))
    request: dict = {"tilts": args.tilts}
    if args.image:
        request["image_b64"] = base64.b64encode(Path(args.image).read_bytes()).decode()
        request["label"] = args.image
    elif args.polygon:
        request["polygon"] = [list(point) for point in args.polygon]
    else:
        request["frames"] = args.frames
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                reference = estimator.call(estimator_protocol.TEACH, **request)
                break
            except CommandError as error:  # a system just started has sent fewer frames than asked to average
                if error.code != "not_enough_frames" or time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        print(f"taught reference {reference.id} ({reference.kind}, {reference.shape[1]} x {reference.shape[0]}"
              + (f", the mean of {reference.frames_averaged} frames" if (reference.frames_averaged or 1) > 1 else "")
              + ")", flush=True)
        if args.tilts:
            return _wait_for_tilt_teach(estimator, reference.id)
    except (ServiceUnavailable, CommandError) as error:
        print(f"semservo teach: {error}", file=sys.stderr)
        return 1
    finally:
        estimator.close()
    return 0


def _wait_for_tilt_teach(estimator, reference_id: str, timeout_s: float = 180.0) -> int:
    """Follow the taught pose's focus sweeps (they run in the background) to their end:
    ``timeout_s`` for each sweep. On a terminal one line counts the frames as they are
    scanned; in a log, a line for each sweep."""
    from semservo.protocol import estimator as estimator_protocol

    started, said, on_terminal = time.monotonic(), None, sys.stdout.isatty()
    while True:
        reference = estimator.call(estimator_protocol.REPORT).reference
        teach = reference.tilt_teach if reference is not None and reference.id == reference_id else None
        if on_terminal and said is not None and (teach is None or teach.state != "sweeping"):
            print(flush=True)  # ends the line the frames were counted on
        if teach is None:
            print("semservo teach: the reference was replaced during its focus sweep", file=sys.stderr)
            return 1
        if teach.state == "done":
            tilt = reference.tilt or {}
            print(f"{taught_sweeps(tilt)}: the taught pose's plane tilts alpha {tilt.get('alpha_deg', 0):+.2f}, beta "
                  f"{tilt.get('beta_deg', 0):+.2f} deg, pinned to +-{tilt.get('alpha_uncertainty_deg', math.nan):.3f} "
                  f"and +-{tilt.get('beta_uncertainty_deg', math.nan):.3f} ({tilt.get('kernels_used')} kernels in "
                  "focus somewhere)")
            return 0
        if teach.state == "failed":
            print(f"semservo teach: the image is taught, not its tilts: {teach.error}", file=sys.stderr)
            return 1
        progress = tilt_teach_progress(teach)
        if on_terminal:
            line = f"{progress}: {teach.scanned} of {teach.frames} frames"
            if line != said:
                newline = said is not None and not said.startswith(progress + ":")
                print(("\n" if newline else "\r") + line + "\033[K", end="", flush=True)
                said = line
        elif progress != said:
            print(progress, flush=True)
            said = progress
        if time.monotonic() > started + timeout_s * teach.sweep:
            if on_terminal:
                print(flush=True)
            print(f"semservo teach: focus sweep {teach.sweep} did not end within {timeout_s:g} s", file=sys.stderr)
            return 1
        time.sleep(0.25)


def command_motion(args: argparse.Namespace) -> int:
    settings = Settings()
    subscriber = MessageSubscriber(connect(settings.estimator.host, settings.estimator.motion_port),
                                   MOTION_TOPIC, MotionEstimate)
    received = 0
    deadline = time.monotonic() + args.timeout
    try:
        while received < args.count and time.monotonic() < deadline:
            estimate = subscriber.receive(timeout_s=0.2)
            if estimate is None:
                continue
            received += 1
            print(f"seq {estimate.seq:6d}  dx {estimate.dx_px:+9.3f} px  dy {estimate.dy_px:+9.3f} px  "
                  f"rot {estimate.rotation_deg:+7.3f} deg  conf {estimate.confidence:.2f}  "
                  f"snr {estimate.snr_db:5.1f} dB  latency {estimate.latency_ms:6.2f} ms")
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
    finally:
        subscriber.close()
    if not received:
        print(f"no motion estimates in {args.timeout:g} s: {_why_no_motion(settings)}", file=sys.stderr)
    return 0 if received else 1


def _why_no_motion(settings: Settings) -> str:
    """Why the estimator published nothing, as far as it says: down, nothing taught, or
    taught but no frames reach it."""
    control = ControlClient(connect(settings.estimator.host, settings.estimator.control_port),
                            timeout_s=min(settings.request_timeout_s, 3.0), retries=0)
    try:
        report = control.request("report")
    except ServiceUnavailable:
        return f"the estimator does not answer on {control.endpoint}: is the system up? (semservo up)"
    except CommandError as error:
        return f"the estimator refused its report: {error.message}"
    finally:
        control.close()
    if not report.get("reference"):
        return "the estimator has no reference taught (semservo teach)"
    return "the estimator has a reference but measured no frame: are frames flowing? (semservo frames)"


def _run_binding(name: str, main, argv: list[str]) -> int:
    """Run a service's main; a port already taken is one line naming the setting that
    moves it (the usual cause is a second semservo on the same machine), not a traceback."""
    try:
        return main(argv)
    except security.SecurityError as error:
        print(f"{name}: refusing to start: {error}", file=sys.stderr)
        return 2
    except (zmq.ZMQError, OSError) as error:
        if error.errno not in (zmq.EADDRINUSE, errno.EADDRINUSE):
            raise
        print(f"{name}: cannot bind its port: {error} (is another semservo running? "
              f"each port is a SEMSERVO_{name.upper()}__*_PORT setting)", file=sys.stderr)
        return 1


def command_service(args: argparse.Namespace) -> NoReturn:
    from semservo.service import end_process

    module = importlib.import_module(spec(args.name).module)
    end_process(_run_binding(args.name, module.main, args.service_args))


def command_fakelab(args: argparse.Namespace) -> int:
    """The simulated lab alone, for a real stage service or a developer's experiments."""
    from services.fakelab.main import main as fakelab_main

    return _run_binding("fakelab", fakelab_main, args.fakelab_args)


#: Commands whose own parser takes every argument after the command's name.
PASS_THROUGH = {"fakelab"}


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
                  f"mean {frame.pixels.mean():7.2f}  {acquisition_text(header).rstrip(', ')}")
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
    finally:
        subscriber.close()
    print(stats.summary(subscriber.counters))
    return 0 if stats.frames else 1


def command_stop(args: argparse.Namespace) -> int:
    """Stop at once from a terminal, without the gateway: the stage first (it holds and
    refuses moves until resumed), then the controller's run."""
    from semservo.protocol import carryable_text
    from semservo.protocol import controller as controller_protocol
    from semservo.protocol import stage as stage_protocol

    settings = Settings()
    # An argument that is not UTF-8 arrives with surrogates, which a message cannot carry.
    reason = carryable_text(args.reason, 500)[0] or "stop requested"
    stage_took = False
    for name, command in (("stage", stage_protocol.STOP), ("controller", controller_protocol.STOP)):
        config = getattr(settings, name)
        port = ServicePort(ControlClient(connect(config.host, config.control_port),
                                         timeout_s=min(settings.request_timeout_s, 2.0), retries=2))
        try:
            reply = port.call(command, reason=reason)
        except (ServiceUnavailable, CommandError) as error:
            print(f"{name}: did not take the stop: {error}", file=sys.stderr)
            continue
        finally:
            port.close()
        if name == "stage":
            stage_took = True
            print(f"stage: {reply.state} ({reply.reason or reason}); it refuses moves until resumed "
                  "(POST /stage/resume, the dashboard, or a start with resume=true)", flush=True)
        else:
            print(f"controller: {reply.state}" + (f", run {reply.run_id}" if reply.run_id else "")
                  + (f" ({reply.reason})" if reply.reason else ""), flush=True)
    return 0 if stage_took else 1


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


def calibration_ports(settings: Settings, *, frame_timeout_s: float = 30.0, truth: bool = True):
    """The stage port, the ``next_frame(after_ns)`` source and, when the simulated lab
    answers, the truth for a :class:`semservo.calibration.Calibrator`; and a closer."""
    from semservo.calibration import CalibrationError

    stage = ControlClient(connect(settings.stage.host, settings.stage.control_port),
                          timeout_s=settings.request_timeout_s, retries=1)
    frames = FrameSubscriber(connect(settings.imageserver.host, settings.imageserver.frames_port),
                             max_message_bytes=settings.max_message_bytes)
    fakelab = ControlClient(connect(settings.fakelab.host, settings.fakelab.control_port), timeout_s=1.0, retries=1)

    def next_frame(after_ns: int):
        deadline = time.monotonic() + frame_timeout_s
        while time.monotonic() < deadline:
            frame = frames.receive(timeout_s=0.2)
            if frame is None:
                continue
            started = frame.header.scan_started_at_ns or frame.header.acquired_at_ns
            if started >= after_ns:
                return frame
        raise CalibrationError(f"no frame scanned after the move within {frame_timeout_s:g} s: "
                               "is the image server running? (semservo health imageserver)")

    simulated = False
    if truth:
        try:
            fakelab.request("health")
            simulated = True
        except ServiceUnavailable:
            simulated = False

    def true_displacement(axis: str):
        channel_key = f"{axis}_um"
        untimed = []

        def truth_of(frame) -> float | None:
            # Frames without the simulator's scan times (a watched folder's files, an
            # adapter's) cannot be matched to its pose: no truth, said once.
            if frame.header.source_interval_s is None:
                if not untimed:
                    untimed.append(frame.header.seq)
                    print("the simulated lab answers, but the frames carry no scan times to ask it the truth by "
                          "(a watched folder's or an adapter's): calibrating without the truth", flush=True)
                return None
            return float(fakelab.request("pose", interval_s=list(frame.header.source_interval_s))[channel_key])

        return truth_of

    def close() -> None:
        for closable in (stage, frames, fakelab):
            closable.close()

    return ServicePort(stage), next_frame, (true_displacement if simulated else None), close


def command_calibrate(args: argparse.Namespace) -> int:
    from semservo.calibration import CalibrationError, Calibrator

    settings = Settings()
    stage, next_frame, truth, close = calibration_ports(settings, frame_timeout_s=args.frame_timeout,
                                                        truth=not args.no_truth)
    config = settings.controller

    def progress(point, done: int, total: int) -> None:
        arrow = "up" if point.direction > 0 else "down"
        truth_text = "" if point.true_displacement_um is None else f"  true {point.true_displacement_um:8.3f} um"
        print(f"[{done:3d}/{total}] {point.voltage:7.2f} V {arrow:<4} {args.axis} {point.displacement_um:8.3f} um"
              f"{truth_text}  across {point.cross_um:+7.3f} um  conf {point.confidence:.2f}", flush=True)

    calibrator = Calibrator(stage, next_frame, axis=args.axis, camera=config.camera_to_stage(),
                            settle_s=args.settle, keyframe_px=args.keyframe_px,
                            truth=truth(args.axis) if truth else None, progress=progress)

    def left_at() -> str:
        if calibrator.last_v is None or calibrator.started_v is None:
            return ""
        return f"; the {args.axis} axis is left at {calibrator.last_v:.2f} V (it was at {calibrator.started_v:.2f} V)"

    try:
        result = calibrator.run(args.low, args.high, args.step)
    except (CalibrationError, CommandError, ServiceUnavailable, ValueError) as error:
        print(f"calibration failed: {error}{left_at()}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"interrupted: nothing written{left_at()}", file=sys.stderr)
        return 130
    finally:
        close()
    problem = result.fit_problem()
    if problem is not None:
        print(f"calibration failed: {problem}; no model written{left_at()}", file=sys.stderr)
        return 1
    out = Path(args.out or f"calibration-{args.axis}.json")
    result.save(out)
    plot = result.plot(out.with_suffix(".png"))
    summary = result.summary()
    print(f"axis {args.axis}: stroke {summary['stroke_um']} um over {args.low:g}..{args.high:g} V, "
          f"loop {summary['loop_width_percent']} % of stroke, fit residual {summary['fit_residual_um'] * 1000:.0f} nm")
    if result.true_loop_width is not None:
        print(f"simulator truth: loop {summary['true_loop_width_percent']} %, measured displacement off the truth "
              f"by {result.true_error_um['mean']} um mean, {result.true_error_um['max']} um max")
    print(f"model written to {out} (use it: SEMSERVO_STAGE__MODEL_FILES='{{\"{args.axis}\": \"{out}\"}}'), "
          f"plot {plot}")
    return 0


#: The demo's jog: (6, -4) um at x1200's pixel; with a sample image the same pixels, at
#: most DEMO_MAX_JOG_UM a side (the stage's travel is ~100 um).
DEMO_OFFSET_UM = (6.0, -4.0)
DEMO_PIXEL_UM = 0.1769
DEMO_MAX_JOG_UM = 8.0
#: --offset's bound: the stage's travel (100 um); its step limit may refuse less, and
#: says how far one move may go.
DEMO_MAX_OFFSET_UM = 100.0
#: How long the demo waits for its run: x, y (and the turn) take seconds to a minute; five
#: degrees of freedom wait on focus sweeps (tens of seconds each, one in two held back as
#: scanned during a tilt move): on a real picture as the sample one run took 265 s, another
#: more than 300.
DEMO_TIMEOUT_S = 300.0
DEMO_TIMEOUT_5DOF_S = 900.0


def command_demo(args: argparse.Namespace) -> int:
    """Teach, displace, position back, report: on the running system, or on one the demo
    starts (simulated hardware) and stops again. A run the demo started never outlives it:
    given up on (``--timeout``) or interrupted, it is stopped."""
    from semservo.client import Client, SemservoError, WaitTimeout, save

    tilts = args.dof == "all"
    turns = args.dof in ("rotation", "all")
    if args.speedup:
        os.environ["SEMSERVO_FAKELAB__SPEEDUP"] = str(args.speedup)
        os.environ["SEMSERVO_STAGE__MAX_RATE_V_PER_S"] = str(stage_rate_for(args.speedup))
    if tilts:  # the tilts are seen through focus: the small-depth-of-field condition
        os.environ.setdefault("SEMSERVO_FAKELAB__PRESET", "tilts")
    sample_options = sample_image.environment_from_arguments(args)
    os.environ.update(sample_options)
    settings = Settings()
    url = args.url or f"http://127.0.0.1:{settings.gateway.http_port}"
    launcher = None
    lab = Client(url, timeout=30)
    run_id, started_here = None, False
    taught, displaced = None, None  # what the demo has done, said if a later step fails
    try:
        try:
            lab.status()
            if sample_options:
                print(f"demo: a system is already running at {url}, with its own sample; the --sample-* options "
                      "apply to a system the demo starts: stop that one, or leave the options out", file=sys.stderr)
                return 2
            print(f"using the running system at {url}"
                  + (" (--speedup applies to a system the demo starts; this one keeps its own)"
                     if args.speedup else ""))
        except SemservoError:
            started_here = True
            print(f"no system at {url}: starting one on simulated hardware (semservo up does the same)")
            if not _sample_image_environment("demo"):
                return 2
            settings = Settings()
            if settings.fakelab.sample_image is not None:
                print(f"   the sample: the picture {settings.fakelab.sample_image} (semservo.simulation.sample_image)")
            launcher = Launcher(settings, out=open(os.devnull, "w") if not args.verbose else sys.stdout)
            launcher.start(timeout_s=120)
        deadline = time.monotonic() + 60
        while lab.status().latest_frame_seq is None:
            if time.monotonic() > deadline:
                print("no frames reach the gateway: is the image server running?", file=sys.stderr)
                return 1
            time.sleep(0.2)
        # Before the teach: a demo that cannot move must not replace the taught reference.
        stage = lab.stage()
        if stage.state == "stopped":
            if not args.resume:
                print(f"demo: the stage is stopped ({stage.reason}); nothing was taught or moved. An operator's stop "
                      f"holds, across restarts too, until someone resumes it: the dashboard's Resume, POST "
                      f"{url}/stage/resume, or this demo again with --resume.", file=sys.stderr)
                return 1
            lab.resume()
            print("   the stage was stopped; resumed (--resume)")
        said = []

        def sweeping(teach) -> None:  # a line for each focus sweep of the teach
            progress = tilt_teach_progress(teach)
            if not said or said[-1] != progress:
                print(f"   {progress}", flush=True)
                said.append(progress)

        if tilts:
            print("1. teaching: the mean of the live frames, and focus sweeps at the taught pose (the tilts; a "
                  "minute or a few) ...", flush=True)
        try:
            reference = lab.teach(frames=args.frames, tilts=tilts, progress=sweeping)
        except SemservoError as error:
            if tilts and error.code == "no_tilt_reference":
                if launcher is not None and sample_options:
                    # Its own system, in the tilts preset: the picture is what cannot show them.
                    hint = ("This picture, under the 'tilts' preset's optics, does not show focus over enough of its "
                            "field to pin the tilts to a tenth of a degree (a texture over the whole field does; a "
                            "few shapes on a dark ground does not). Try another picture, or `--dof rotation` (x, y "
                            "and the turn about the beam).")
                else:
                    hint = ("A running system in another preset cannot measure them: start it with `semservo up "
                            "--preset tilts`, or let the demo start its own (stop the running one).")
                print(f"demo: {error.message}\n   The tilts are measured from focus, so they need a depth of field "
                      f"small against the depth a tilt spans across the field (the 'tilts' preset: 3.5 um). {hint}",
                      file=sys.stderr)
                return 1
            raise
        taught = reference.id
        print(f"1. taught reference {reference.id} (mean of {args.frames} live frames)"
              + (f"; its tilts from {taught_sweeps(reference.tilt)}: alpha {reference.tilt['alpha_deg']:+.3f}, beta "
                 f"{reference.tilt['beta_deg']:+.3f} deg, pinned to +-{reference.tilt['alpha_uncertainty_deg']:.3f} "
                 f"and +-{reference.tilt['beta_uncertainty_deg']:.3f} ({reference.tilt['kernels_used']} kernels in "
                 "focus somewhere)" if tilts else ""))
        offset = args.offset
        pixel_nm = reference.get("pixel_size_nm") or (reference.get("acquisition") or {}).get("pixel_size_nm")
        if offset is None:
            # 34, -23 px: (6, -4) um at the default x1200, the same part of the field at any
            # scale (a sample image's own), within what one jog of the stage may be.
            offset = DEMO_OFFSET_UM
            if pixel_nm and settings.fakelab.sample_image is not None:
                offset = tuple(float(np.clip(value / DEMO_PIXEL_UM * pixel_nm / 1000, -DEMO_MAX_JOG_UM,
                                             DEMO_MAX_JOG_UM)) for value in DEMO_OFFSET_UM)
        lab.move(x_um=offset[0], y_um=offset[1])
        displaced = f"({offset[0]:+.3g}, {offset[1]:+.3g}) um"
        in_pixels = f" = ({offset[0] * 1000 / pixel_nm:+.1f}, {offset[1] * 1000 / pixel_nm:+.1f}) px" if pixel_nm else ""
        print(f"2. displaced the stage by ({offset[0]:+.3g}, {offset[1]:+.3g}) um{in_pixels}, as an operator's "
              "joystick would")
        dofs = ["x", "y"]
        if turns:
            angles = {"rotation_deg": args.turn}
            if tilts:
                angles.update(tilt_x_deg=args.tilt[0], tilt_y_deg=args.tilt[1])
            lab.rotate(**angles)
            displaced += " and turned by " + ", ".join(f"{value:+g} deg" for value in angles.values())
            dofs += ["gamma", "alpha", "beta"] if tilts else ["gamma"]
            print("   turned the sample by " + ", ".join(f"{value:+g} deg {name}" for name, value in zip(
                ("gamma", "alpha", "beta"), (args.turn, *(args.tilt if tilts else ())))))
        time.sleep(args.settle)
        # A 5-DOF run acts on every fresh frame while it waits for each focus sweep: more iterations.
        run = lab.start(tolerance_px=args.tolerance, dofs=dofs, law=args.law,
                        **({"max_iterations": 600} if tilts else {}))
        run_id = run.run_id
        print(f"3. positioning run {run_id} started ({', '.join(dofs)}; {args.law} law; tolerance {args.tolerance:g} px); "
              "waiting ...", flush=True)
        timeout = args.timeout if args.timeout is not None else (DEMO_TIMEOUT_5DOF_S if tilts else DEMO_TIMEOUT_S)
        result = lab.wait(run_id, timeout=timeout, stop_on_timeout=True)
        partial = int((result.outcome or {}).get("partial_frames") or 0)
        of_them = f", {partial} of them partial: a scan's rows after a move" if partial else ""
        source_s = (result.outcome or {}).get("source_time_to_target_s")
        faster = (f", the simulated lab running {args.speedup:g} x faster"
                  if started_here and args.speedup and args.speedup != 1 else "")
        clocks = (f" (wall clock; {source_s:.1f} s on the microscope's: its frames' own times{faster})"
                  if source_s is not None else "")
        print(f"4. {result.state} after {result.iterations} iterations ({result.fresh_frames or 0} fresh frames"
              f"{of_them}) in {result.duration_s or 0:.1f} s{clocks}"
              f"{' (' + result.reason + ')' if result.reason else ''}")
        if result.final_error_px is not None:
            judged = ("the position law's estimate" if args.law == "position"
                      else "the mean of the last fresh frames")
            print(f"   estimated final error {result.final_error_px:.3f} px ({judged}: what the run judges "
                  "convergence on)")
        truth = result.truth
        if truth:
            shown = truth.get("view_error_norm_px", truth["error_norm_px"])
            if "view_error_norm_px" in truth:  # tilted: the image's error is the view's, not the stage's
                print(f"   true final error (simulator) {shown:.3f} px = {shown * 1000 * truth['pixel_size_um']:.1f} nm "
                      f"in the image (where the taught centre's content is); the stage's x, y "
                      f"{truth['error_norm_px']:.3f} px (they differ by the tilt cradle's pivot lever under the "
                      "residual tilt, which x, y make up for)")
            else:
                print(f"   true final error (simulator) {shown:.3f} px = "
                      f"{1000 * float(np.hypot(*truth['error_um'])):.1f} nm")
            angles = truth.get("error_deg") or {}
            if turns and angles:
                print("   true final angles (simulator): " + ", ".join(
                    f"{name} {angles[key]:+.3f} deg" for name, key in (("gamma", "rotation_deg"), ("alpha", "tilt_x_deg"),
                                                                       ("beta", "tilt_y_deg")) if key in angles))
            if result.state == "converged":
                # The run's own tolerances (its record's settings), else the defaults it ran with.
                from semservo.protocol.controller import RunSettings

                ran = {**{name: field.default for name, field in RunSettings.model_fields.items()},
                       **(result.settings or {})}
                tolerances = {"rotation_deg": ("gamma", ran["tolerance_deg"]),
                              "tilt_x_deg": ("alpha", ran["tolerance_tilt_deg"]),
                              "tilt_y_deg": ("beta", ran["tolerance_tilt_deg"])}
                over = ([f"{shown:.3f} px over {args.tolerance:g} px"] if shown > args.tolerance else []) + [
                    f"{name} {abs(angles[key]):.3f} deg over {limit:g} deg" for key, (name, limit) in tolerances.items()
                    if turns and key in angles and abs(angles[key]) > limit]
                if over:
                    # Where the texture is off the image's centre (a cluster of particles), the
                    # x, y at the centre is carried from it through the turn: 0.04 deg of turn
                    # error at 240 px is 0.17 px, which the run's x, y estimate does not see.
                    why = "; ".join(
                        (["the turn's own measurement error, carried to the image's centre from where the texture "
                          "lies (0.04 deg at 240 px off-centre is 0.17 px)"] if turns else [])
                        + (["the tilts' own measurement error (each sweep's and the teach's, which the run cannot "
                            "see)"] if tilts else [])
                        + ["the stage's vibration and creep over the last frames' scans and the estimates' noise"])
                    hint = ("; with the paper's law, the run setting converge_on=\"each\" lands further inside: see "
                            "the README's positioning benchmark" if args.law == "paper" else "")
                    print(f"   (the truth is outside the tolerance: {'; '.join(over)}. The run stops when its "
                          f"*estimates* are within it; the truth also carries {why}{hint})")
        runs_dir = Path(settings.controller.runs_dir)
        runs_dir.mkdir(parents=True, exist_ok=True)
        report = save(lab.run_report(run_id), runs_dir / f"{run_id}-report.png")
        print(f"   report (error, cost, voltages per iteration): {report}")
        if launcher is None:
            print(f"   the run's record: {url}/runs/{run_id}  (dashboard: {url}/)")
        return 0 if result.state == "converged" else 1
    except WaitTimeout as error:
        # The give-up stopped the stage (no run outlives the demo), and a stop holds, across
        # restarts too, until someone resumes it: say how, or the next demo only refuses.
        print(f"demo gave up: {error.message}. The stage holds stopped until resumed: run the next demo with "
              f"--resume, or the dashboard's Resume, or POST {url}/stage/resume; --timeout waits longer.",
              file=sys.stderr)
        return 1
    except SemservoError as error:
        print(f"demo failed: {error}", file=sys.stderr)
        if run_id is None and displaced is not None:
            print(f"   no run was started: the stage stays displaced by {displaced} from the view taught as "
                  f"{taught}", file=sys.stderr)
        elif run_id is None and taught is not None:
            print(f"   nothing moved; the estimator keeps the reference {taught} this demo taught", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        if run_id is not None:
            with contextlib.suppress(SemservoError):  # the system is going down with it
                lab.stop("the demo was interrupted")
        return 130
    finally:
        lab.close()
        if launcher is not None:
            launcher.stop()


def command_reproduce(args: argparse.Namespace) -> int:
    """The paper's experiments on the simulated lab, with the baselines (semservo.reproduce)."""
    from semservo import reproduce

    try:
        path = reproduce.run(Path(args.out), quick=args.quick, only=args.only, fresh=args.fresh)
    except ValueError as error:
        print(f"reproduce: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: finished experiments are kept; run the same command to go on", file=sys.stderr)
        return 130
    print(f"tables beside the paper's, and figures: {path}")
    return 0


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
    up.add_argument("--frames", type=_count, default=20, help="frames --check waits for (default 20)")
    up.add_argument("--timeout", type=_positive, default=60.0,
                    help="seconds to wait for health and for --check (default 60)")
    up.add_argument("--restart", action="store_true", help="restart a service that dies (with back-off)")
    up.add_argument("--status-every", type=_positive, default=5.0, help="seconds between status lines (default 5)")
    up.add_argument("--source", choices=["sim", "replay", "watch", "adapter"],
                    help="frames from the simulated SEM (default), a replay, a watched folder or a lab's adapter")
    up.add_argument("--preset", choices=sorted(PRESETS), metavar="PRESET",
                    help=f"simulated condition: {', '.join(PRESETS)} (default optimal; tilts: the small depth of "
                         "field the tilt measurement needs)")
    up.add_argument("--speedup", type=_positive, help="simulated time runs this many times faster (default 1)")
    up.add_argument("--replay-dir", help="replay this folder of frames instead (default folder: the 2013 recording)")
    up.add_argument("--glob", help="only files matching this pattern are frames, e.g. 'frame*' or '*.tif' (a replayed "
                                   "folder, and a watched one with --watch-dir)")
    up.add_argument("--fps", type=_positive, help="replay frame rate (default 10)")
    loop = up.add_mutually_exclusive_group()
    loop.add_argument("--loop", dest="loop", action="store_true", default=None, help="replay in a loop (default)")
    loop.add_argument("--once", dest="loop", action="store_false", help="replay once")
    up.add_argument("--magnification", type=_positive, help="magnification of the replayed frames")
    up.add_argument("--watch-dir", help="frames from the folder an SEM's software saves into: each new file is "
                                        "published once it is complete (see docs/instruments.md)")
    sample_image.add_arguments(up)
    up.add_argument("--sim-saves-frames", action="store_true",
                    help="with --watch-dir: the simulated SEM saves its frames there, as a vendor's software "
                         "would (the whole path without a microscope)")
    up.set_defaults(handler=command_up)

    service = commands.add_parser("service", help="run one service in the foreground",
                                  description="Run one service; options after its name go to the service "
                                              "(see 'semservo service NAME --help').")
    service.add_argument("name", choices=[s.name for s in SERVICES])
    service.add_argument("service_args", nargs=argparse.REMAINDER, help="options for the service")
    service.set_defaults(handler=command_service)

    fakelab = commands.add_parser(
        "fakelab", help="run the simulated lab alone (SEM + NV 40/3 emulator); prints its serial port",
        add_help=False)
    fakelab.add_argument("fakelab_args", nargs=argparse.REMAINDER)
    fakelab.set_defaults(handler=command_fakelab)

    frames = commands.add_parser(
        "frames", help="watch a frame stream and print each header",
        description="Subscribe to the image server's frames (or another frame stream) and print each frame's "
                    "header: sequence number, size, pixel size, dwell, working distance, source times. The way to "
                    "check what a real instrument's frames carry.")
    frames.add_argument("--count", type=_count, default=10, help="frames to print (default 10)")
    frames.add_argument("--timeout", type=_positive, default=30.0, help="give up after this many seconds (default 30)")
    frames.add_argument("--endpoint", help="frames address (default: the image server's)")
    frames.set_defaults(handler=command_frames)

    estimate = commands.add_parser(
        "estimate", help="measure motion between image files",
        description="Print the motion of each IMAGE against REFERENCE (Fourier phase correlation, "
                    "paper section II): dx_px, dy_px (content moved right/down), rotation_deg "
                    "(counter-clockwise as displayed), confidence, snr_db, elapsed_ms. Unreadable "
                    "files are reported on stderr after the readable ones are printed; the exit "
                    "code is then 1.")
    estimate.add_argument("reference", help="the taught image (PNG/TIFF), or the mask with --mask")
    estimate.add_argument("images", nargs="+", metavar="IMAGE", help="current images")
    estimate.add_argument("--no-rotation", action="store_true", help="translation only")
    estimate.add_argument("--mask", action="store_true",
                          help="REFERENCE is a binary mask of the object (paper case 6)")
    estimate.add_argument("--polygon", type=_polygon, metavar="'X,Y X,Y ...'",
                          help="use the polygon of these corner points on REFERENCE as a mask reference")
    estimate.add_argument("--scan-averaged", action="store_true",
                          help="average the shift over the scan's bands of rows, as the estimator service does for "
                               "live frames: each band is a snapshot at its own time, so stage vibration faster than "
                               "a frame is not weighted by where the texture lies (semservo.estimation.raster)")
    estimate.add_argument("--precision", choices=["fast", "full"], default="full",
                          help="sub-pixel fit at full resolution (full, default) or on the 2x search pair (fast)")
    estimate.add_argument("--json", action="store_true", help="one JSON object per line")
    estimate.add_argument("--crop", choices=["auto", "common", "none"], default="auto",
                          help="images of different sizes: auto (default) compares the common region, from the top "
                               "left, when they differ by up to 10 %% (a data bar cut from one file only), saying "
                               "so; common does it whatever the difference; none refuses")
    estimate.set_defaults(handler=command_estimate)

    teach = commands.add_parser(
        "teach", help="teach the running estimator a reference",
        description="Teach the live frame (default; --frames averages several), an image file, or a polygon mask. "
                    "The estimator's reference is the one the gateway, the dashboard and every run use, whoever "
                    "taught it.")
    source = teach.add_mutually_exclusive_group()
    source.add_argument("--frames", type=_teach_frames, default=1,
                        help="average the last N live frames, 1..16 (default 1; the stage must stand still)")
    source.add_argument("--image", help="PNG/TIFF file to use as the reference")
    source.add_argument("--polygon", type=_polygon, metavar="'X,Y X,Y ...'",
                        help="corner points of a mask on the live frame")
    teach.add_argument("--tilts", action="store_true", help="also sweep the focus at the taught pose, so runs can "
                                                            "servo the tilts (waits for the sweep, with progress)")
    teach.add_argument("--during-run", action="store_true",
                       help="teach even while a run servos (it then fails: its reference changed), or when the "
                            "controller does not answer; without it such a teach is refused, as the gateway refuses "
                            "a teach during a run")
    teach.set_defaults(handler=command_teach)

    motion = commands.add_parser(
        "motion", help="watch the estimator's motion stream",
        description="Subscribe to the estimator's motion estimates (each frame against the taught reference) and "
                    "print them: dx, dy (px, content moved right/down), rotation (degrees), confidence, SNR and the "
                    "estimation time. Needs a running system with a taught reference (semservo teach).")
    motion.add_argument("--count", type=_count, default=10, help="estimates to print (default 10)")
    motion.add_argument("--timeout", type=_positive, default=30.0, help="give up after this many seconds (default 30)")
    motion.set_defaults(handler=command_motion)

    calibrate = commands.add_parser(
        "calibrate", help="sweep a stage axis, measure it in the images, fit its hysteresis model",
        description="On the running system (semservo up): walk one axis to LOW volts, sweep it up to HIGH and "
                    "back in STEP volt steps through the stage service, measure each step's motion from the "
                    "SEM frames (Fourier registration against key frames), and fit the lab's model: one "
                    "fourth-order polynomial V = p(d) per hysteresis branch. Writes the model as JSON (the "
                    "stage service loads it through SEMSERVO_STAGE__MODEL_FILES) and a plot of the loop. On "
                    "the simulated lab the true displacement is read too and the fit compared with it. Use "
                    "a magnification at which the whole stroke moves the image by less than its width.")
    calibrate.add_argument("--axis", choices=["x", "y"], default="x", help="stage axis (default x)")
    calibrate.add_argument("--low", type=_finite, default=-19.0, help="sweep from this voltage (default -19)")
    calibrate.add_argument("--high", type=_finite, default=96.0,
                           help="up to this voltage (default 96: the lab's model covers -19..96 V, 0..100 um)")
    calibrate.add_argument("--step", type=_positive, default=2.5, help="volts per step (default 2.5)")
    calibrate.add_argument("--settle", type=_number(0), default=0.3,
                           help="seconds to wait after each step before a frame counts (default 0.3)")
    calibrate.add_argument("--keyframe-px", type=_positive, default=32.0,
                           help="start a new key frame after the image moved this far (default 32)")
    calibrate.add_argument("--frame-timeout", type=_positive, default=30.0,
                           help="give up when no new frame comes within this many seconds (default 30)")
    calibrate.add_argument("--no-truth", action="store_true", help="do not ask the simulated lab for the truth")
    calibrate.add_argument("--out", help="model file to write (default calibration-AXIS.json; plot beside it)")
    calibrate.set_defaults(handler=command_calibrate)

    demo = commands.add_parser(
        "demo", help="teach, displace the stage, position back, print the result",
        description="Through the REST API (the gateway): teach the live view, jog the stage away, start a "
                    "positioning run, wait, and print iterations, time, the estimated and (on simulated "
                    "hardware) the true final error, with the path of the run's report. Uses the running "
                    "system, or starts one on simulated hardware and stops it afterwards.")
    demo.add_argument("--url", help="gateway address (default http://127.0.0.1:HTTP_PORT)")
    demo.add_argument("--offset", type=_number(-DEMO_MAX_OFFSET_UM, DEMO_MAX_OFFSET_UM), nargs=2,
                      metavar=("X_UM", "Y_UM"),
                      help="how far to displace the stage (default 6 -4 um: 34, -23 px at x1200; with a sample image "
                           "the same pixels at its scale, at most 8 um a side)")
    demo.add_argument("--tolerance", type=_positive, default=0.1, help="converged under this error, px (default 0.1)")
    demo.add_argument("--dof", choices=["xy", "rotation", "all"], default="xy",
                      help="degrees of freedom: xy (default), rotation (x, y and the turn about the beam) or all five "
                           "(x, y, gamma and the tilts alpha, beta, from focus sweeps; a demo that starts the system "
                           "starts it in the small-depth-of-field 'tilts' preset)")
    demo.add_argument("--law", choices=["position", "paper"], default="position",
                      help="the law: position-based (default: a few moves, and one tilt move per measurement) or the "
                           "paper's (eq. 30-37; see the README's time-to-target table)")
    demo.add_argument("--turn", type=_finite, default=3.0,
                      help="with --dof rotation/all: turn about the beam, degrees (default 3)")
    demo.add_argument("--tilt", type=_finite, nargs=2, default=(2.0, -1.5), metavar=("ALPHA", "BETA"),
                      help="with --dof all: tilts about x and y, degrees (default 2 -1.5)")
    demo.add_argument("--frames", type=_teach_frames, default=4,
                      help="live frames averaged into the reference (default 4)")
    demo.add_argument("--settle", type=_number(0), default=1.0, help="seconds to wait after the jog (default 1)")
    demo.add_argument("--timeout", type=_positive, default=None,
                      help=f"give up on the run after this many seconds (default {DEMO_TIMEOUT_S:g}; "
                           f"{DEMO_TIMEOUT_5DOF_S:g} with --dof all, whose focus sweeps take tens of seconds each)")
    demo.add_argument("--speedup", type=_positive,
                      help="when the demo starts the system: simulated time this much faster (default 1)")
    demo.add_argument("--verbose", action="store_true", help="show the services' logs when the demo starts them")
    demo.add_argument("--resume", action="store_true", help="let a stage an operator stopped move again first (a "
                                                            "stop holds until someone resumes, across restarts too)")
    sample_image.add_arguments(demo)
    demo.set_defaults(handler=command_demo)

    from semservo.reproduce import EXPERIMENTS

    reproduce = commands.add_parser(
        "reproduce", help="re-run the paper's experiments (Tables I-IV, Figs. 4, 8-11) with its baselines",
        description="Re-run the paper's experiments on the simulated lab, semservo and the baselines the paper "
                    "compared against (photometric visual servoing, dense optical flow, keypoints) closing the same "
                    "loop, and write the tables beside the paper's numbers with the figures. Finished experiments "
                    "are kept and skipped when run again (resumable); --fresh redoes them.")
    reproduce.add_argument("--quick", action="store_true", help="a reduced run: a few minutes on 2 cores")
    reproduce.add_argument("--only", nargs="+", choices=EXPERIMENTS, metavar="NAME",
                           help=f"run only these: {', '.join(EXPERIMENTS)}")
    reproduce.add_argument("--out", default="docs/reproduction", help="where the report goes (default docs/reproduction)")
    reproduce.add_argument("--fresh", action="store_true", help="redo experiments that have results already")
    reproduce.set_defaults(handler=command_reproduce)

    stop = commands.add_parser(
        "stop", help="stop at once: the stage first, then the run (without the gateway)",
        description="Tell the stage service to hold (it refuses moves until an operator resumes it) and the "
                    "controller to end its run as stopped, straight over their control sockets: works when the "
                    "gateway or the dashboard does not. Exit status 1 if the stage did not take it.")
    stop.add_argument("--reason", default="stopped from the command line", help="said in the run's record")
    stop.set_defaults(handler=command_stop)

    health = commands.add_parser(
        "health", help="ask services for their health",
        description="Ask each service over its control socket for its health: up or not, its endpoints and its "
                    "counters (requests, refusals as rejected_<rule>, ...). Exit status 1 if any does not answer.")
    health.add_argument("names", nargs="*", type=_service_name, metavar="NAME",
                        help=f"services (default: all): {', '.join(s.name for s in SERVICES)}")
    health.set_defaults(handler=command_health)

    keys = commands.add_parser(
        "keys", help="make CURVE keys: every ZeroMQ socket authenticated and encrypted (two-PC deployments)",
        description="Make the CURVE keys of a deployment in DIR (kept if they exist): server.key(_secret) for "
                    "every binding socket, client.key(_secret) for every connecting one, and authorized/ with "
                    "the client keys servers accept. Then set SEMSERVO_CURVE_KEYS_DIR=DIR on every PC; a PC "
                    "that only runs lab scripts needs client.key, client.key_secret and server.key.")
    keys.add_argument("dir", type=Path, help="folder for the keys (e.g. ~/.config/semservo/keys)")
    keys.set_defaults(handler=command_keys)
    return parser


def command_keys(args: argparse.Namespace) -> int:
    made = security.make_keys(args.dir)
    for name, path in made.items():
        print(f"{name:>10}: {path}")
    print(f"set SEMSERVO_CURVE_KEYS_DIR={args.dir.resolve()} on every PC of this deployment")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in PASS_THROUGH:  # e.g. semservo fakelab --preset noisy --help
        return command_fakelab(argparse.Namespace(fakelab_args=argv[1:]))
    args = build_parser().parse_args(argv)
    return args.handler(args)


if __name__ == "__main__":
    sys.exit(main())
