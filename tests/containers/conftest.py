"""The whole system as containers on fake hardware: one compose stack (docker-compose.yml)
for this package, brought up by ``./dev compose up`` itself with the offline image, on a
free published port, and taken down (records volume included) when the package is done.

The engine is Docker where one answers, else podman (``./dev test`` installs Debian's
podman and runc). No test here is skipped for want of an engine: the fixture fails and
says what is missing. Tests talk to the system only as users do: ``semservo.client``
through the published port, the ``semservo`` CLI inside containers, and the engine's own
commands (inspect, kill, network disconnect); the engine calls go through
``deploy/stack.py``, the module ``./dev compose`` runs."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from semservo.client import Client

ROOT = Path(__file__).resolve().parents[2]

#: Building the image on a fresh machine (Debian base, wheelhouse, dependencies) takes
#: minutes and counts in the first test's setup; a cached build seconds. Each test's own
#: waits are bounded well below this.
TIMEOUT_S = 900


def pytest_collection_modifyitems(config, items):
    here = Path(__file__).parent
    for item in items:
        if here in Path(item.fspath).parents:
            item.add_marker(pytest.mark.timeout(TIMEOUT_S))


def _load_stack_module():
    spec = importlib.util.spec_from_file_location("semservo_deploy_stack", ROOT / "deploy" / "stack.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


stack_module = _load_stack_module()


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class System:
    """The running stack as a lab user and an operator see it."""

    def __init__(self, stack, env: dict[str, str]):
        self.stack = stack
        self.env = env
        self.engine = stack.engine

    # the contract: ./dev compose ...
    def dev_compose(self, *args: str, timeout: float = 900) -> subprocess.CompletedProcess:
        result = subprocess.run([str(ROOT / "dev"), "compose", *args], cwd=ROOT, env=self.env, capture_output=True,
                                text=True, timeout=timeout)
        assert result.returncode == 0, f"./dev compose {' '.join(args)} failed:\n{result.stdout}\n{result.stderr}"
        return result

    def client(self, timeout: float = 30.0) -> Client:
        """A lab script's client: the printed URL and the token file (both change on up)."""
        return Client(self.stack.url, token=self.stack.token, timeout=timeout)

    # the operator's view, through the engine
    def info(self, service: str) -> dict:
        return self.stack.containers()[service]

    def exec(self, service: str, *command: str, check: bool = True) -> subprocess.CompletedProcess:
        return self.engine.run("exec", self.stack.container(service), *command, check=check, timeout=120)

    def ready_stage(self, lab: Client) -> None:
        """Tests share the stack: a stage left held or stopped by another is resumed."""
        if lab.stage()["state"] != "ready":
            response = lab.http.post("/stage/resume")
            assert response.status_code == 200, response.text
        assert lab.stage()["state"] == "ready"

    def wait_frames(self, lab: Client, after_seq: int | None = None, timeout_s: float = 60.0) -> int:
        """Until the gateway has a frame newer than ``after_seq``; its seq."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            seq = lab.status()["latest_frame_seq"]
            if seq is not None and (after_seq is None or seq > after_seq):
                return seq
            time.sleep(0.3)
        raise AssertionError(f"no new frame at the gateway within {timeout_s:.0f} s (last {after_seq})")

    def displace_and_start(self, lab: Client, offset=(5.0, -4.0), **settings) -> dict:
        """Teach the live view, jog the stage away as an operator would, start a run."""
        self.ready_stage(lab)
        self.wait_frames(lab)
        lab.teach(frames=1)
        lab.move(x_um=offset[0], y_um=offset[1])
        time.sleep(1.0)
        return lab.start(**settings)

    def wait_iterations(self, lab: Client, run_id: str, count: int, timeout_s: float = 90.0) -> None:
        """Until the run has made ``count`` moves (its record says so); it must still be servoing."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            record = lab.run(run_id)
            assert record["state"] == "servoing", (record["state"], record["reason"])
            if record["iterations"] >= count:
                return
            time.sleep(0.3)
        raise AssertionError(f"run {run_id} made fewer than {count} moves in {timeout_s:.0f} s")


@pytest.fixture(scope="package")
def system(tmp_path_factory):
    try:
        engine = stack_module.detect_engine()
    except stack_module.StackError as error:
        pytest.fail(f"the container tests need an engine: {error}", pytrace=False)
    # One project per checkout (two worktrees on one machine do not collide); a stack
    # left by an interrupted session is replaced by `up`.
    project = "semservo-test-" + hashlib.sha256(str(ROOT).encode()).hexdigest()[:8]
    folder = tmp_path_factory.mktemp("compose")
    env = {**os.environ, "SEMSERVO_COMPOSE_PROJECT": project, "SEMSERVO_COMPOSE_DIR": str(folder),
           "SEMSERVO_HTTP_PUBLISH": f"127.0.0.1:{free_port()}", "SEMSERVO_BUILD": "offline",
           "SEMSERVO_ENGINE": engine.name}
    stack = stack_module.Stack(engine, project=project, folder=folder, http_publish=env["SEMSERVO_HTTP_PUBLISH"])
    system = System(stack, env)
    try:
        up = system.dev_compose("up")
        # What ./dev compose up promises to print: the gateway's URL and where the token is.
        assert stack.url in up.stdout and str(stack.token_file) in up.stdout, up.stdout
        print(up.stdout, up.stderr, file=sys.stderr)
        yield system
    finally:  # also when up failed or timed out half-way: nothing is left running
        system.dev_compose("down", "--volumes", timeout=300)


ARTIFACTS = ROOT / "test-artifacts" / "containers"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.when == "call":
        item.failed_call = report.failed


@pytest.fixture(autouse=True)
def logs_on_failure(request, system):
    """A failing test leaves each container's state and log tail in
    test-artifacts/containers/TEST/: CI keeps no engine to ask afterwards."""
    yield
    if not getattr(request.node, "failed_call", False):
        return
    folder = ARTIFACTS / request.node.name
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "containers.json").write_text(json.dumps(system.stack.containers(), indent=2))
    for service in stack_module.SERVICES:
        result = system.engine.run("logs", "--tail", "300", system.stack.container(service), check=False)
        (folder / f"{service}.log").write_bytes(result.stdout + result.stderr)


@pytest.fixture(autouse=True)
def no_silent_restarts(request, system):
    """The restart policy hides a crash: a container restarted during a test that did not
    kill it fails that test (a test that kills one says so: ``restarts_expected``)."""
    before = {service: (info["id"], info["restarts"]) for service, info in system.stack.containers().items()}
    yield
    expected = getattr(request.function, "restarts_expected", set())
    restarted = {service: info["restarts"] - before[service][1] for service, info in system.stack.containers().items()
                 if service in before and info["id"] == before[service][0] and service not in expected
                 and info["restarts"] != before[service][1]}
    assert not restarted, f"containers restarted during the test (crashed?): {restarted}; see ./dev compose logs"


@pytest.fixture
def lab(system):
    with system.client() as client:
        yield client
        # A test that failed half-way may leave a run servoing: the next one must not find it.
        try:
            if client.status()["state"] == "servoing":
                client.stop("the test that started this run has ended")
        except Exception as error:  # noqa: BLE001 - cleanup; the test's own outcome stands
            print(f"could not stop a leftover run: {error}", file=sys.stderr)


def unauthorized(url: str, path: str, token: str | None) -> int:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return httpx.post(url + path, json={"x_um": 1.0}, headers=headers, timeout=10).status_code
