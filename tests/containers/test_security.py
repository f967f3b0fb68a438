"""CURVE on every ZeroMQ socket, the token on the gateway: a container on the same
networks without the keys, or with keys of its own, gets no frame and no answer; with
the deployment's keys the same commands work (so it is the keys, not the network)."""

from __future__ import annotations

import concurrent.futures

from tests.containers.conftest import stack_module, unauthorized

PEERS = {f"SEMSERVO_{name.upper()}__HOST": name
         for name in ("fakelab", "imageserver", "estimator", "stage", "controller", "gateway")}
PROBE = ("semservo frames --count 1 --timeout 3; echo frames=$?; "
         "semservo health imageserver stage controller fakelab; echo health=$?")


def _probe(system, keys: str) -> str:
    """The probe in a fresh container on the microscope and work networks: no keys,
    keys it makes itself, or the deployment's keys mounted."""
    env = [argument for name, host in PEERS.items() for argument in ("-e", f"{name}={host}")]
    env += ["-e", "SEMSERVO_REQUEST_TIMEOUT_S=1"]
    mounts, script = [], PROBE
    if keys == "own":
        script = "semservo keys /tmp/keys >/dev/null && export SEMSERVO_CURVE_KEYS_DIR=/tmp/keys; " + PROBE
    elif keys == "deployment":
        mounts = ["-v", f"{system.stack.keys_dir}:/keys:ro", "-e", "SEMSERVO_CURVE_KEYS_DIR=/keys"]
    result = system.engine.run(
        "run", "--rm", "--network", system.stack.network("microscope"), "--network", system.stack.network("work"),
        *env, *mounts, stack_module.IMAGE, "sh", "-c", script, check=False, timeout=180)
    return result.stdout.decode() + result.stderr.decode()


def test_a_container_without_the_keys_gets_no_frame_and_no_answer(system):
    with concurrent.futures.ThreadPoolExecutor(3) as pool:
        none, own, deployment = pool.map(lambda keys: _probe(system, keys), ("none", "own", "deployment"))
    for output in (none, own):
        assert "frames=1" in output and "no frames" in output, output
        assert "health=1" in output and output.count("DOWN") == 4, output
    assert "frames=0" in deployment and "health=0" in deployment and "DOWN" not in deployment, deployment


def test_only_the_stage_reaches_the_amplifier(system):
    """The emulated NV 40/3's TCP port is bound on the serial network alone."""
    reach = "import socket; socket.create_connection(('fakelab', 5592), timeout=3).close()"
    assert system.exec("stage", "python3", "-c", reach, check=False).returncode == 0
    for service in ("imageserver", "gateway", "estimator", "controller"):
        assert system.exec(service, "python3", "-c", reach, check=False).returncode != 0, service


def test_the_gateway_wants_its_token(system):
    url = system.stack.url
    assert unauthorized(url, "/stage/move", None) == 401
    assert unauthorized(url, "/stage/move", "not-the-token") == 401
