"""No Docker engine runs here, so the compose file is checked by reading it: every
service it names exists, runs a real entry point, and publishes the settings' ports."""

from __future__ import annotations

import importlib
import tomllib
from pathlib import Path

import pytest
import yaml

from semservo.cli import build_parser
from semservo.config import Settings
from semservo.launcher import SERVICES, spec

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def container_settings(service: dict, monkeypatch) -> Settings:
    for key in [k for k in __import__("os").environ if k.startswith("SEMSERVO_")]:
        monkeypatch.delenv(key)
    for key, value in (service.get("environment") or {}).items():
        monkeypatch.setenv(key, str(value))
    return Settings()


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


def test_published_ports_match_the_settings_model(compose, monkeypatch):
    for name, service in compose["services"].items():
        settings = container_settings(service, monkeypatch)
        published = {int(mapping.split(":")[1]) for mapping in service["ports"]}
        service_settings = getattr(settings, name)
        assert published == {value for key, value in service_settings.model_dump().items() if key.endswith("_port")}
        assert set(service["depends_on"]) <= set(compose["services"]) if "depends_on" in service else True
        assert service_settings.host == name  # peers reach it by compose name
        assert settings.bind_host == "0.0.0.0"
    imageserver = container_settings(compose["services"]["imageserver"], monkeypatch).imageserver
    assert str(imageserver.replay_dir) == "/data/sem-run-2013"


def test_every_container_uses_curve_keys(compose, monkeypatch):
    """Containers bind 0.0.0.0: each one must carry the CURVE keys, or it refuses to start."""
    from semservo.security import require_keys_off_loopback

    for name, service in compose["services"].items():
        settings = container_settings(service, monkeypatch)
        assert settings.curve_keys_dir == Path("/keys"), name
        assert any(str(volume).endswith(":/keys:ro") for volume in service["volumes"]), name
        require_keys_off_loopback(settings)
