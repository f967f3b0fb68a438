"""The compose file and the container settings, read against this code without an
engine (tests/containers runs them): every service it names exists and runs a real
entry point, the networks are the paper's two PCs with the serial cable apart, every
container has the CURVE keys and a healthcheck, and podman gets the settings it needs."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml

from semservo.cli import build_parser
from semservo.config import Settings
from semservo.launcher import SERVICES, spec
from semservo.security import require_keys_off_loopback

ROOT = Path(__file__).resolve().parents[2]
WORK_PC = {"estimator", "controller", "stage", "gateway"}


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def container_settings(service: dict, monkeypatch) -> Settings:
    for key in [k for k in os.environ if k.startswith("SEMSERVO_")]:
        monkeypatch.delenv(key)
    for key, value in (service.get("environment") or {}).items():
        monkeypatch.setenv(key, str(value))
    return Settings()


def networks_of(service: dict) -> set[str]:
    networks = service.get("networks") or []
    return set(networks if isinstance(networks, list) else networks.keys())


def test_compose_lists_exactly_the_services_that_exist(compose):
    assert set(compose["services"]) == {s.name for s in SERVICES}


def test_every_command_is_a_real_entry_point(compose):
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    for name, service in compose["services"].items():
        program, *arguments = service["command"]
        assert program == "semservo" and scripts["semservo"] == "semservo.cli:main"
        parsed = build_parser().parse_args(arguments)  # the CLI accepts it
        assert parsed.name == name
        module = importlib.import_module(spec(parsed.name).module)
        assert callable(module.main)
        module.build_parser().parse_args(parsed.service_args)  # and so does the service


def test_build_files_exist(compose):
    for service in compose["services"].values():
        assert (ROOT / service["build"]["context"] / service["build"]["dockerfile"]).is_file()
        assert service["image"] == f"semservo:{tomllib.loads((ROOT / 'pyproject.toml').read_text())['project']['version']}"
    for offline in ("offline-deps.Dockerfile", "offline.Dockerfile", "containers.conf", "stack.py"):
        assert (ROOT / "deploy" / offline).is_file()


def test_the_networks_are_the_two_pcs_and_the_serial_cable(compose):
    services = compose["services"]
    members = {network: {name for name, service in services.items() if network in networks_of(service)}
               for network in compose["networks"]}
    assert members["microscope"] == {"fakelab", "imageserver"}  # PC 1
    assert members["work"] == WORK_PC | {"imageserver"}  # PC 2, and the frames crossing to it
    assert members["serial"] == {"fakelab", "stage"}  # the amplifier's cable
    assert members["simulator"] == {"fakelab", "gateway"}  # the fake lab's truth: no real instrument has it
    # Nothing but the stage reaches the amplifier: its port is bound on the serial network alone.
    fakelab = services["fakelab"]
    alias = fakelab["environment"]["SEMSERVO_FAKELAB__SERIAL_BIND_HOST"]
    assert alias in fakelab["networks"]["serial"]["aliases"]
    assert "serial_bind_host" in Settings().fakelab.model_dump()  # a typo would be ignored silently
    assert compose["x-semservo"]["environment"]["SEMSERVO_STAGE__SERIAL_URL"] == f"socket://{alias}:5592"


def test_only_the_gateways_http_port_is_published(compose, monkeypatch):
    for name, service in compose["services"].items():
        settings = container_settings(service, monkeypatch)
        assert getattr(settings, name).host == name  # peers reach it by compose name
        assert settings.bind_host == "0.0.0.0"
        if name != "gateway":
            assert not service.get("ports"), name
    gateway = compose["services"]["gateway"]
    settings = container_settings(gateway, monkeypatch)
    assert gateway["ports"] == [f"${{SEMSERVO_HTTP_PUBLISH:-{settings.gateway.http_port}}}:{settings.gateway.http_port}"]
    assert settings.gateway.http_host == "0.0.0.0"
    assert str(settings.gateway.database).startswith("/data/runs/")


def test_every_container_uses_curve_keys(compose, monkeypatch):
    """Containers bind 0.0.0.0: each one must carry the CURVE keys, or it refuses to start."""
    for name, service in compose["services"].items():
        settings = container_settings(service, monkeypatch)
        assert settings.curve_keys_dir == Path("/keys"), name
        assert any(str(volume).endswith(":/keys:ro") for volume in service["volumes"]), name
        require_keys_off_loopback(settings)


def test_every_service_has_its_own_health_command_as_healthcheck(compose):
    for name, service in compose["services"].items():
        test = service["healthcheck"]["test"]
        assert test[0] == "CMD" and test[-3:] == ["semservo", "health", name], test
        parsed = build_parser().parse_args(test[-2:])
        assert parsed.names == [name]
        assert service["restart"] == "unless-stopped"


def test_records_and_stage_state_live_on_the_volume(compose, monkeypatch):
    for name in ("stage", "controller", "gateway"):
        assert "runs:/data/runs" in compose["services"][name]["volumes"]
    settings = [container_settings(compose["services"][name], monkeypatch) for name in ("stage", "controller")]
    assert settings[0].stage.state_dir == Path("/data/runs") and settings[1].controller.runs_dir == Path("/data/runs")


def test_podman_gets_its_settings_from_the_project(compose):
    assert compose["x-podman"] == {"name_separator_compat": True, "in_pod": False}
    conf = tomllib.loads((ROOT / "deploy" / "containers.conf").read_text())
    assert conf["engine"]["runtime"] == "runc" and conf["engine"]["cgroup_manager"] == "cgroupfs"
    assert set(conf["containers"]["default_ulimits"]) == {"nofile=1024:1024", "nproc=4096:4096"}
    assert conf["network"]["network_backend"] == "netavark"


def test_podman_compose_is_pinned():
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["test"]
    assert any(requirement.startswith("podman-compose==") for requirement in extras)


def test_a_missing_engine_is_one_line_saying_what_to_install(tmp_path):
    result = subprocess.run([sys.executable, str(ROOT / "deploy" / "stack.py"), "up"], capture_output=True,
                            text=True, env={"PATH": str(tmp_path), "HOME": str(tmp_path)}, timeout=60)
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "install podman" in lines[0] and "Docker" in lines[0], result.stderr


def test_the_two_pc_compose_files_split_the_services(monkeypatch):
    """deploy/pc1-microscope.yml and deploy/pc2-work.yml: every service but the fake lab,
    each once, with the keys, a healthcheck and settings the model accepts."""
    pc1 = yaml.safe_load((ROOT / "deploy" / "pc1-microscope.yml").read_text())["services"]
    pc2 = yaml.safe_load((ROOT / "deploy" / "pc2-work.yml").read_text())["services"]
    assert set(pc1) == {"imageserver"} and set(pc2) == WORK_PC
    for name, service in {**pc1, **pc2}.items():
        assert service["command"] == ["semservo", "service", name]
        assert service["healthcheck"]["test"][-3:] == ["semservo", "health", name]
        settings = container_settings(service, monkeypatch)
        require_keys_off_loopback(settings)
        assert settings.curve_keys_dir == Path("/keys")
    assert {"5550:5550", "5551:5551"} == set(pc1["imageserver"]["ports"])
    stage = container_settings(pc2["stage"], monkeypatch).stage
    assert stage.serial_url == "/dev/nv40" and stage.rotation_stage == "none"
    assert pc2["stage"]["devices"][0].endswith(":/dev/nv40")
    assert container_settings(pc2["estimator"], monkeypatch).imageserver.host.startswith("${SEMSERVO_PC1")
