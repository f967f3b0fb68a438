"""``semservo up``: start every service as a child process and watch over them.

Small on purpose. Process-supervision libraries were weighed (supervisor, circus,
honcho): supervisor and circus are daemons with their own config files and control
sockets, honcho runs a Procfile but neither waits for health nor restarts. What is
needed here is a few dozen lines on :mod:`subprocess`: spawn, prefix logs, ask each
service's control socket for ``health`` until it answers, report a death at once,
optionally restart with back-off, and stop a group at a time with SIGTERM then SIGKILL.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, TextIO

from semservo.config import Settings, StageSettings, connect
from semservo.messages import Health
from semservo.transport import ControlClient, ServiceUnavailable


@dataclass(frozen=True)
class ServiceSpec:
    """A service the launcher knows: its module and where it listens."""

    name: str
    module: str
    control: Callable[[Settings], str]
    endpoints: Callable[[Settings], dict[str, str]]
    summary: str
    #: Stands in for the lab's instruments: started, and healthy, before the rest.
    hardware: bool = False


#: Every service that exists, in start order. A service is listed here only once it is
#: written: never a placeholder.
SERVICES: tuple[ServiceSpec, ...] = (
    ServiceSpec(
        name="fakelab",
        module="services.fakelab.main",
        control=lambda s: connect(s.fakelab.host, s.fakelab.control_port),
        endpoints=lambda s: {
            "SEM scans (REP)": connect(s.fakelab.host, s.fakelab.scan_port),
            "NV 40/3 serial (TCP)": f"socket://{s.fakelab.host}:{s.fakelab.serial_tcp_port}",
            "control (REP)": connect(s.fakelab.host, s.fakelab.control_port),
        },
        summary="simulated SEM and emulated NV 40/3 amplifier in one world",
        hardware=True,
    ),
    ServiceSpec(
        name="imageserver",
        module="services.imageserver.main",
        control=lambda s: connect(s.imageserver.host, s.imageserver.control_port),
        endpoints=lambda s: {
            "frames (PUB)": connect(s.imageserver.host, s.imageserver.frames_port),
            "control (REP)": connect(s.imageserver.host, s.imageserver.control_port),
        },
        summary="SEM frames from the simulated SEM or a replayed recording",
    ),
    ServiceSpec(
        name="estimator",
        module="services.estimator.main",
        control=lambda s: connect(s.estimator.host, s.estimator.control_port),
        endpoints=lambda s: {
            "motion (PUB)": connect(s.estimator.host, s.estimator.motion_port),
            "control (REP)": connect(s.estimator.host, s.estimator.control_port),
        },
        summary="Fourier motion estimates of each frame against the taught reference",
    ),
    ServiceSpec(
        name="stage",
        module="services.stage.main",
        control=lambda s: connect(s.stage.host, s.stage.control_port),
        endpoints=lambda s: {
            "control (REP)": connect(s.stage.host, s.stage.control_port),
            ("NV 40/3 serial" if s.stage.driver == "nv40" else f"stage driver ({s.stage.driver})"): s.stage.serial_url,
        },
        summary="the NV 40/3 on RS-232: limits, watchdog, stop",
    ),
    ServiceSpec(
        name="controller",
        module="services.controller.main",
        control=lambda s: connect(s.controller.host, s.controller.control_port),
        endpoints=lambda s: {
            "status (PUB)": connect(s.controller.host, s.controller.status_port),
            "control (REP)": connect(s.controller.host, s.controller.control_port),
        },
        summary="the visual servoing law: motion in, stage moves out",
    ),
    ServiceSpec(
        name="gateway",
        module="services.gateway.main",
        control=lambda s: connect(s.gateway.host, s.gateway.control_port),
        endpoints=lambda s: {
            "REST API, docs, dashboard (HTTP)": f"http://{s.gateway.http_host}:{s.gateway.http_port}/",
            "control (REP)": connect(s.gateway.host, s.gateway.control_port),
        },
        summary="REST API (FastAPI), run records (SQLite), dashboard",
    ),
)


def spec(name: str) -> ServiceSpec:
    for candidate in SERVICES:
        if candidate.name == name:
            return candidate
    raise KeyError(f"no service {name!r}; services: {', '.join(s.name for s in SERVICES)}")


class LaunchError(RuntimeError):
    """A service could not be started (it exited, or never reported healthy)."""


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    # Linux: if the launcher is killed outright, its children get SIGTERM too.
    with contextlib.suppress(OSError):  # not glibc: the child simply lacks the safety net
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


@dataclass
class Child:
    spec: ServiceSpec
    process: subprocess.Popen
    started: float
    restarts: int = 0
    reported_exit: bool = False
    reader: threading.Thread | None = field(default=None, repr=False)


class Launcher:
    def __init__(
        self,
        settings: Settings,
        specs: tuple[ServiceSpec, ...] = SERVICES,
        *,
        service_args: dict[str, list[str]] | None = None,
        restart: bool = False,
        max_restarts: int = 5,
        out: TextIO = sys.stdout,
        color: bool | None = None,
    ):
        self.settings = settings
        self.specs = specs
        self.service_args = service_args or {}
        self.restart = restart
        self.max_restarts = max_restarts
        self.out = out
        self.color = out.isatty() if color is None else color
        self.children: dict[str, Child] = {}
        self._print_lock = threading.Lock()
        # One caller at a time changes the children: a supervising thread and a restart
        # asked for by hand must not both replace the same dead child.
        self._children_lock = threading.RLock()

    # -- output ---------------------------------------------------------------
    def say(self, text: str, *, name: str = "semservo") -> None:
        width = max(len(s.name) for s in self.specs) if self.specs else 8
        prefix = f"{name:<{max(width, 8)}} | "
        if self.color:
            palette = ("36", "33", "35", "32", "34", "31")
            names = [s.name for s in self.specs]
            code = palette[names.index(name) % len(palette)] if name in names else "1"
            prefix = f"\x1b[{code}m{prefix}\x1b[0m"
        with self._print_lock:
            for line in text.splitlines() or [""]:
                self.out.write(prefix + line + "\n")
            self.out.flush()

    def _stream(self, child: Child) -> None:
        for line in child.process.stdout:
            self.say(line.rstrip("\n"), name=child.spec.name)

    # -- lifecycle ------------------------------------------------------------
    def _spawn(self, service: ServiceSpec) -> Child:
        command = [sys.executable, "-m", "semservo", "service", service.name, *self.service_args.get(service.name, [])]
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        process = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            env=env,
            start_new_session=True,  # Ctrl-C reaches the launcher, which stops children in order
            preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
        )
        child = Child(spec=service, process=process, started=time.monotonic())
        child.reader = threading.Thread(target=self._stream, args=(child,), daemon=True, name=f"log-{service.name}")
        child.reader.start()
        return child

    def health(self, name: str, *, timeout_s: float = 0.5, retries: int = 1) -> Health:
        client = ControlClient(spec(name).control(self.settings), timeout_s=timeout_s, retries=retries)
        try:
            return Health.model_validate(client.request("health"))
        finally:
            client.close()

    def _wait_healthy(self, child: Child, deadline: float) -> Health:
        while True:
            code = child.process.poll()
            if code is not None:
                raise LaunchError(f"{child.spec.name} exited with code {code} while starting (its log is above)")
            with contextlib.suppress(ServiceUnavailable):  # not answering yet: ask again
                health = self.health(child.spec.name, timeout_s=0.3)
                if health.pid != child.process.pid:
                    # Another semservo holds the port: its answer says nothing of ours.
                    raise LaunchError(
                        f"another process (pid {health.pid}, another semservo?) answers as {child.spec.name} on "
                        f"{child.spec.control(self.settings)}: stop it, or give this one other ports "
                        f"(SEMSERVO_{child.spec.name.upper()}__*_PORT)")
                if health.healthy:
                    return health
            if time.monotonic() > deadline:
                raise LaunchError(f"{child.spec.name} did not report healthy in time")
            time.sleep(0.05)

    def start(self, timeout_s: float = 30.0) -> None:
        """Start the hardware (the fake lab) and wait until it is healthy, then every
        other service at once, and wait until each reports healthy, in start order (each
        within ``timeout_s`` of its turn).

        The hardware first, as a lab's instruments are on before its software: the stage
        reads the rotation stage once, at its first connection. The rest at once, not one
        after another: most of a service's start is importing its libraries (FastAPI,
        numba, FFTW), and spawned together they share the cores instead of queueing on
        one; they connect lazily and say in their health what they still wait for."""
        try:
            for wave in ([s for s in self.specs if s.hardware], [s for s in self.specs if not s.hardware]):
                for service in wave:
                    self.children[service.name] = self._spawn(service)
                for service in wave:
                    health = self._wait_healthy(self.children[service.name], time.monotonic() + timeout_s)
                    self.say(f"{service.name} healthy (pid {health.pid}, {health.state})")
        except BaseException:
            self.stop()
            raise

    def restart_service(self, name: str, timeout_s: float = 30.0) -> Health:
        """Stop one service (SIGTERM, then SIGKILL) and start it again; its health."""
        with self._children_lock:
            replacement = self._replace(name)
        return self._wait_healthy(replacement, time.monotonic() + timeout_s)

    def _replace(self, name: str) -> Child:
        child = self.children[name]
        if child.process.poll() is None:
            child.process.terminate()
            try:
                child.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                child.process.kill()
                child.process.wait()
        child.reported_exit = True
        replacement = self._spawn(child.spec)
        self.children[name] = replacement
        return replacement

    def table(self) -> str:
        rows = [("service", "pid", "what", "where")]
        for name, child in self.children.items():
            for label, endpoint in child.spec.endpoints(self.settings).items():
                rows.append((name, str(child.process.pid), label, endpoint))
        widths = [max(len(row[i]) for row in rows) for i in range(4)]
        return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(row, widths)) for row in rows)

    def supervise(self) -> list[str]:
        """Look at every child once: report deaths at once, restart when asked.

        Returns the names of services that are down now.
        """
        with self._children_lock:
            return self._supervise()

    def _supervise(self) -> list[str]:
        down = []
        for name, child in self.children.items():
            code = child.process.poll()
            if code is None:
                continue
            if not child.reported_exit:
                self.say(f"!! {name} died (exit code {code}) after {time.monotonic() - child.started:.1f} s")
                child.reported_exit = True
            if self.restart and child.restarts < self.max_restarts:
                backoff = min(5.0, 0.5 * 2**child.restarts)
                if time.monotonic() - child.started >= backoff:
                    replacement = self._spawn(child.spec)
                    replacement.restarts = child.restarts + 1
                    self.children[name] = replacement
                    self.say(f"restarting {name} (restart {replacement.restarts} of {self.max_restarts})")
                    continue
            down.append(name)
        return down

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the children a group at a time (:data:`STOP_ORDER`), each group together:
        SIGTERM, then SIGKILL to any still running ``timeout_s`` later. The gateway and
        the controller end their runs while the stage and the estimator they talk to
        are still there; the stage lets go of the amplifier while it still answers."""
        for group in _stop_groups(list(self.children)):
            children = {name: self.children[name] for name in group}
            for child in children.values():
                if child.process.poll() is None:
                    child.process.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + timeout_s
            for name, child in children.items():
                try:
                    code = child.process.wait(max(0.0, deadline - time.monotonic()))
                    self.say(f"{name} stopped (exit code {code})")
                except subprocess.TimeoutExpired:
                    child.process.kill()
                    child.process.wait()
                    self.say(f"{name} did not stop in {timeout_s:.0f} s; killed")
            for child in children.values():
                if child.reader is not None:
                    child.reader.join(timeout=1.0)


#: The order :meth:`Launcher.stop` stops the services in, a group at a time: a service
#: stops only once those it talks to while stopping are still up (the controller ends a
#: run through the stage and the estimator; the stage releases the amplifier, which the
#: fake lab emulates). A group stops together: each service takes a few tenths of a
#: second to end (threads, sockets; :func:`semservo.service.end_process` skips the
#: interpreter's teardown, which took as long again), and one by one that was six
#: seconds per stack.
STOP_ORDER: tuple[tuple[str, ...], ...] = (("gateway", "controller"), ("estimator", "imageserver", "stage"),
                                           ("fakelab",))


def _stop_groups(names: list[str]) -> list[list[str]]:
    """``names`` (in start order) as :data:`STOP_ORDER`'s groups; a service it does not
    name stops on its own, after them, in reverse start order."""
    groups = [[name for name in group if name in names] for group in STOP_ORDER]
    named = {name for group in STOP_ORDER for name in group}
    groups += [[name] for name in reversed(names) if name not in named]
    return [group for group in groups if group]


# -- a whole system on simulated hardware, on fresh loopback ports ---------------------
# For the whole-stack benchmarks, ``semservo reproduce`` and the tests: each starts its own
# system beside any other one running, so every port is chosen anew.

#: Every port a service binds, by a short name, and the setting that holds it.
PORT_SETTINGS = {
    "frames": "SEMSERVO_IMAGESERVER__FRAMES_PORT", "control": "SEMSERVO_IMAGESERVER__CONTROL_PORT",
    "motion": "SEMSERVO_ESTIMATOR__MOTION_PORT", "estimator_control": "SEMSERVO_ESTIMATOR__CONTROL_PORT",
    "fakelab_control": "SEMSERVO_FAKELAB__CONTROL_PORT", "scan": "SEMSERVO_FAKELAB__SCAN_PORT",
    "serial_tcp": "SEMSERVO_FAKELAB__SERIAL_TCP_PORT", "stage_control": "SEMSERVO_STAGE__CONTROL_PORT",
    "controller_control": "SEMSERVO_CONTROLLER__CONTROL_PORT", "controller_status": "SEMSERVO_CONTROLLER__STATUS_PORT",
    "gateway_http": "SEMSERVO_GATEWAY__HTTP_PORT", "gateway_control": "SEMSERVO_GATEWAY__CONTROL_PORT",
}

#: Ports already handed out by this process, never handed out twice (a service started
#: earlier may still be letting go of its port).
_handed_out: set[int] = set()
_port_picker = random.Random()


def _ephemeral_range() -> tuple[int, int]:
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 32768, 60999  # Linux's default


def free_port() -> int:
    """A loopback port free now, chosen *below* the kernel's ephemeral range.

    A port the kernel picked for us (bind to 0) lies inside the ephemeral range, so in
    the moment between choosing it and the service binding it, any outgoing connection
    (every ZeroMQ connect, every HTTP client) may be given it as its local port: CI once
    lost a test to exactly that. Ports below the range are never given out that way.
    """
    ephemeral_low, _ = _ephemeral_range()
    low, high = 15000, max(15000 + 2000, ephemeral_low - 1)
    for _ in range(500):
        port = _port_picker.randint(low, high)
        if port in _handed_out:
            continue
        with socket.socket() as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
        _handed_out.add(port)
        return port
    raise RuntimeError(f"no free loopback port in {low}..{high}")


def fresh_port_environment() -> dict[str, str]:
    """SEMSERVO_* variables giving every service a fresh loopback port (the stage service
    finds the emulated NV 40/3 on the chosen TCP port) and a fresh folder for what the
    stage service keeps across restarts (no system inherits another's armed or stopped
    stage). The folder is removed when this process exits (the services it starts are
    stopped by then). Returns the variables; the caller sets them."""
    chosen = {name: free_port() for name in PORT_SETTINGS}
    variables = {variable: str(chosen[name]) for name, variable in PORT_SETTINGS.items()}
    variables["SEMSERVO_STAGE__SERIAL_URL"] = f"socket://127.0.0.1:{chosen['serial_tcp']}"
    state_dir = tempfile.mkdtemp(prefix="semservo-stage-")
    atexit.register(shutil.rmtree, state_dir, ignore_errors=True)
    variables["SEMSERVO_STAGE__STATE_DIR"] = state_dir
    return variables


def stage_rate_for(speedup: float) -> float:
    """The stage's voltage rate limit (V/s, wall time) for a lab running ``speedup`` times
    faster: simulated time runs faster, so commands come faster in wall time, and the
    default limit is a limit per simulated second."""
    return StageSettings.model_fields["max_rate_v_per_s"].default * speedup


def faster_lab_environment(speedup: float, fps: float = 100.0) -> dict[str, str]:
    """The simulated lab's clock ``speedup`` times faster, the stage's rate limit scaled
    with it (as ``semservo up --speedup`` does), the image server as fast as ``fps``."""
    return {"SEMSERVO_FAKELAB__SPEEDUP": str(speedup),
            "SEMSERVO_STAGE__MAX_RATE_V_PER_S": str(stage_rate_for(speedup)), "SEMSERVO_IMAGESERVER__FPS": str(fps)}


@contextlib.contextmanager
def environment(variables: dict[str, str]):
    """``os.environ`` with ``variables`` set (the children inherit them), restored after."""
    saved = {name: os.environ.get(name) for name in variables}
    os.environ.update(variables)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


@contextlib.contextmanager
def simulated_system(folder: Path, *, speedup: float = 20, fps: float = 100, restart: bool = False,
                     out: TextIO | None = None, timeout_s: float = 90.0, **settings: str):
    """The whole system on simulated hardware: the launcher, fresh loopback ports, the lab
    ``speedup`` x faster, its records in ``folder``; ``settings`` are more SEMSERVO_*
    variables (a sample image's too: ``SEMSERVO_FAKELAB__SAMPLE_IMAGE``, with the
    estimator's depth of field derived from its scale as ``semservo up`` does). Yields
    (launcher, settings); everything is stopped afterwards, and the environment is as it
    was."""
    from semservo.simulation.sample_image import system_environment

    folder = Path(folder)
    fresh = fresh_port_environment()
    variables = {**fresh, **faster_lab_environment(speedup, fps),
                 "SEMSERVO_CONTROLLER__RUNS_DIR": str(folder / "runs"),
                 "SEMSERVO_GATEWAY__DATABASE": str(folder / "runs" / "semservo.sqlite"), **settings}
    with environment(variables):
        # With a sample image: what follows from its scale (as `semservo up` sets it),
        # unless set; and a picture that cannot be used is refused here, saying why.
        derived = {key: value for key, value in system_environment(Settings()).items() if key not in os.environ}
    with environment({**variables, **derived}):
        resolved = Settings()
        log = out or (folder / "services.log").open("w")
        launcher = Launcher(resolved, restart=restart, max_restarts=20, out=log)
        try:
            launcher.start(timeout_s=timeout_s)
            yield launcher, resolved
        finally:
            launcher.stop()
            if out is None:
                log.close()
            # The stage's state folder made for this system (not one the caller chose):
            # removed now, not only at exit (a test session starts hundreds).
            if variables["SEMSERVO_STAGE__STATE_DIR"] == fresh["SEMSERVO_STAGE__STATE_DIR"]:
                shutil.rmtree(fresh["SEMSERVO_STAGE__STATE_DIR"], ignore_errors=True)
