"""semservo as containers: build the image (online, or offline from Debian packages and a
wheelhouse), bring docker-compose.yml up on fake hardware with fresh CURVE keys and a
generated API token, wait until every service's own health command answers, take it down.

    ./dev compose up        build what is missing, start, wait, print the gateway's URL
    ./dev compose down      stop and remove the containers (the records volume stays;
                            --volumes removes it too)
    ./dev compose health    run every service's health command now, one line each
    ./dev compose build     build the image only (--offline / --online to choose)
    ./dev compose ps|logs   the compose command of the engine in use, for this project
    ./dev compose test      the container tests (tests/containers)

The engine: ``docker compose`` where a Docker engine answers, else ``podman-compose``
under the project's ``deploy/containers.conf`` (named by ``CONTAINERS_CONF``). Settings,
from the environment:

    SEMSERVO_ENGINE          docker | podman (default: the first that answers)
    SEMSERVO_BUILD           auto | online | offline (default auto: online when a registry
                             answers, else offline)
    SEMSERVO_COMPOSE_PROJECT compose project name (default semservo)
    SEMSERVO_COMPOSE_DIR     where keys, token and state go (default .compose/PROJECT)
    SEMSERVO_HTTP_PUBLISH    the gateway's published port, [IP:]PORT (default 8000)
    SEMSERVO_CACHE           base image recipe cache and wheelhouses (default ~/.cache/semservo)
    SEMSERVO_DEBIAN_MIRROR   for debootstrap (default http://deb.debian.org/debian)

The tests in tests/containers drive the stack through this module's :class:`Stack`.
Only the standard library and the engine's command line are used here.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import hashlib
import json
import os
import platform
import secrets
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COMPOSE_FILE = ROOT / "docker-compose.yml"
CONTAINERS_CONF = ROOT / "deploy" / "containers.conf"
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
VERSION = PYPROJECT["project"]["version"]
IMAGE = f"semservo:{VERSION}"
#: Every service of docker-compose.yml, in start order.
SERVICES = ("fakelab", "imageserver", "estimator", "stage", "controller", "gateway")
#: The user the services run as in the image (deploy/Dockerfile, offline-deps.Dockerfile).
CONTAINER_UID = 1000
SOURCE_LABEL = "org.semservo.source"

#: The offline base: Debian bookworm's own Python (3.11), nothing else.
DEBIAN_SUITE = "bookworm"
BASE_PACKAGES = ("python3", "python3-venv")
TARGET_PYTHON = "3.11"
#: Bumped when the base recipe or the wheelhouse recipe changes (the cache keys).
RECIPE_VERSION = "1"

INSTALL_HINT = ("no container engine answers: install podman (Debian: apt-get install podman runc netavark "
                "aardvark-dns iptables debootstrap) or Docker with its compose plugin")


class StackError(RuntimeError):
    """Something the user must act on, said in one line."""


def say(message: str) -> None:
    print(f"compose: {message}", file=sys.stderr, flush=True)


def _digest(*parts: str | bytes) -> str:
    hasher = hashlib.sha256()
    for part in parts:
        hasher.update(part.encode() if isinstance(part, str) else part)
        hasher.update(b"\0")
    return hasher.hexdigest()[:16]


def _run(command: list[str], *, env: dict | None = None, check: bool = True, capture: bool = True,
         timeout: float | None = None, input: bytes | None = None) -> subprocess.CompletedProcess:
    result = subprocess.run(command, env=env, capture_output=capture, timeout=timeout, input=input)
    if check and result.returncode != 0:
        # stdout first: a build's own error (pip's, on stderr) is its last words, and the
        # message keeps the tail.
        output = ((result.stdout or b"") + (result.stderr or b"")).decode(errors="replace").strip()
        raise StackError(f"{' '.join(map(str, command[:4]))} ... failed ({result.returncode}): {output[-2000:]}")
    return result


# -- the engine ---------------------------------------------------------------------------
@dataclass
class Engine:
    """``docker`` (with ``docker compose``) or ``podman`` (with ``podman-compose`` and the
    project's containers.conf)."""

    name: str

    @property
    def env(self) -> dict[str, str]:
        env = dict(os.environ)
        if self.name == "podman":
            env["CONTAINERS_CONF"] = str(CONTAINERS_CONF)
        return env

    def cli(self, *args: str) -> list[str]:
        return [self.name, *args]

    def run(self, *args: str, check: bool = True, timeout: float | None = 120, input: bytes | None = None,
            capture: bool = True) -> subprocess.CompletedProcess:
        return _run(self.cli(*args), env=self.env, check=check, timeout=timeout, input=input, capture=capture)

    def compose_command(self, project: str) -> list[str]:
        if self.name == "docker":
            return ["docker", "compose", "-f", str(COMPOSE_FILE), "-p", project]
        return [podman_compose(), "-f", str(COMPOSE_FILE), "-p", project]

    def image_labels(self, image: str) -> dict[str, str] | None:
        """The image's labels, or None when there is no such image."""
        result = self.run("image", "inspect", image, check=False)
        if result.returncode != 0:
            return None
        info = json.loads(result.stdout)[0]
        return (info.get("Config") or {}).get("Labels") or info.get("Labels") or {}

    def has_image(self, image: str) -> bool:
        return self.image_labels(image) is not None


def podman_compose() -> str:
    """podman-compose beside this Python (the project's venv pins it), else on PATH."""
    beside = Path(sys.executable).parent / "podman-compose"
    found = str(beside) if beside.exists() else shutil.which("podman-compose")
    if not found:
        raise StackError("podman-compose is missing: ./dev installs it (pyproject.toml's test extras), "
                         "or pip install podman-compose==1.6.0")
    return found


def docker_answers() -> bool:
    if not shutil.which("docker"):
        return False
    try:
        info = subprocess.run(["docker", "info", "--format", "{{.ServerVersion}}"], capture_output=True, timeout=15)
        compose = subprocess.run(["docker", "compose", "version"], capture_output=True, timeout=15)
    except (subprocess.TimeoutExpired, OSError):
        return False
    # podman-docker's `docker` is podman itself: that is the podman path, with its settings.
    podman_shim = b"podman" in (info.stdout + info.stderr).lower()
    return info.returncode == 0 and compose.returncode == 0 and not podman_shim


def podman_answers() -> bool:
    if not shutil.which("podman"):
        return False
    try:
        result = subprocess.run(["podman", "info", "--format", "{{.Host.OCIRuntime.Name}}"], capture_output=True,
                                timeout=30, env={**os.environ, "CONTAINERS_CONF": str(CONTAINERS_CONF)})
    except (subprocess.TimeoutExpired, OSError):
        return False
    return result.returncode == 0


def detect_engine() -> Engine:
    wanted = os.environ.get("SEMSERVO_ENGINE", "").strip().lower()
    if wanted not in ("", "docker", "podman"):
        raise StackError(f"SEMSERVO_ENGINE must be docker or podman, not {wanted!r}")
    if wanted in ("", "docker") and docker_answers():
        return Engine("docker")
    if wanted == "docker":
        raise StackError("SEMSERVO_ENGINE=docker but no Docker engine (with the compose plugin) answers")
    if podman_answers():
        podman_compose()  # says what is missing now rather than half-way
        return Engine("podman")
    raise StackError(INSTALL_HINT)


# -- images -------------------------------------------------------------------------------
def cache_dir() -> Path:
    return Path(os.environ.get("SEMSERVO_CACHE") or Path.home() / ".cache" / "semservo")


def _source_files() -> list[Path]:
    files = [ROOT / "pyproject.toml", ROOT / "README.md"]
    for folder in ("shared", "services"):
        files += sorted(path for path in (ROOT / folder).rglob("*") if path.is_file()
                        and "__pycache__" not in path.parts and not any(p.endswith(".egg-info") for p in path.parts))
    return files


def source_key(*extra: str) -> str:
    """What the app image is made of: the project's files and the recipe that built it."""
    parts: list[str | bytes] = list(extra)
    for path in _source_files():
        parts += [str(path.relative_to(ROOT)), path.read_bytes()]
    return _digest(*parts)


def _machine() -> str:
    return {"amd64": "x86_64", "arm64": "aarch64"}.get(platform.machine().lower(), platform.machine().lower())


def _debian_arch() -> str:
    return {"x86_64": "amd64", "aarch64": "arm64"}.get(_machine(), _machine())


def base_tag() -> str:
    recipe = _digest(RECIPE_VERSION, DEBIAN_SUITE, "minbase", ",".join(BASE_PACKAGES), _debian_arch())
    return f"semservo-base:{DEBIAN_SUITE}-{recipe}"


def _as_root(command: list[str]) -> list[str]:
    if os.geteuid() == 0:
        return command
    if shutil.which("sudo"):
        return ["sudo", "-n", *command]
    raise StackError(f"{command[0]} needs root: run as root (or with sudo)")


def build_base(engine: Engine) -> str:
    """The base image from Debian packages (debootstrap), imported into the engine."""
    tag = base_tag()
    if engine.has_image(tag):
        return tag
    if not shutil.which("debootstrap") and not Path("/usr/sbin/debootstrap").exists():
        raise StackError("the offline image needs debootstrap (Debian: apt-get install debootstrap)")
    debootstrap = shutil.which("debootstrap") or "/usr/sbin/debootstrap"
    mirror = os.environ.get("SEMSERVO_DEBIAN_MIRROR", "http://deb.debian.org/debian")
    started = time.monotonic()
    say(f"building the base image {tag}: debootstrap {DEBIAN_SUITE} (minbase, {', '.join(BASE_PACKAGES)}) ...")
    packages = cache_dir() / "debootstrap" / _debian_arch()
    packages.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="semservo-base-"))
    rootfs = work / "rootfs"
    try:
        _run(_as_root([debootstrap, "--variant=minbase", f"--include={','.join(BASE_PACKAGES)}",
                       f"--arch={_debian_arch()}", f"--cache-dir={packages}", DEBIAN_SUITE, str(rootfs), mirror]),
             timeout=1800)
        # What a container never needs: package caches, documentation, the host's resolver.
        _run(_as_root(["sh", "-c", "cd \"$1\" && rm -rf var/cache/apt/*.bin var/lib/apt/lists/* usr/share/doc "
                                   "usr/share/man usr/share/info usr/share/locale etc/resolv.conf "
                                   "etc/hostname", "-", str(rootfs)]))
        tar = subprocess.Popen(_as_root(["tar", "-C", str(rootfs), "-c", "."]), stdout=subprocess.PIPE)
        try:
            imported = subprocess.run(engine.cli("import", "-", tag), stdin=tar.stdout, capture_output=True,
                                      env=engine.env, timeout=600)
        finally:
            tar.stdout.close()
            tar.wait()
        if imported.returncode != 0 or tar.returncode != 0:
            raise StackError(f"importing the base image failed: {imported.stderr.decode(errors='replace')[-1000:]}")
    finally:
        _run(_as_root(["rm", "-rf", str(work)]), check=False)
    say(f"base image {tag} built in {time.monotonic() - started:.0f} s")
    return tag


def _platform_tags() -> list[str]:
    """Every manylinux tag Debian bookworm's glibc (2.36) runs, newest first."""
    machine = _machine()
    tags = [f"manylinux_2_{minor}_{machine}" for minor in range(36, 16, -1)]
    if machine == "x86_64":
        tags += ["manylinux2014_x86_64", "manylinux2010_x86_64", "manylinux1_x86_64"] + \
                [f"manylinux_2_{minor}_x86_64" for minor in range(16, 4, -1)]
    else:
        tags += [f"manylinux2014_{machine}"]
    return tags


def requirements() -> list[str]:
    return list(PYPROJECT["project"]["dependencies"])


def _build_requires() -> list[str]:
    return list(PYPROJECT["build-system"]["requires"])


def wheelhouse_key() -> str:
    return _digest(RECIPE_VERSION, TARGET_PYTHON, _machine(), *requirements(), *_build_requires())


def deps_tag() -> str:
    """The dependencies image's tag: the base, the pins (the wheelhouse) and its recipe."""
    dockerfile = ROOT / "deploy" / "offline-deps.Dockerfile"
    return f"semservo-deps:{_digest(base_tag(), wheelhouse_key(), dockerfile.read_bytes())}"


def offline_key() -> str:
    return source_key(deps_tag(), (ROOT / "deploy" / "offline.Dockerfile").read_text())


def online_key() -> str:
    return source_key("online", (ROOT / "deploy" / "Dockerfile").read_text())


def wheelhouse() -> Path:
    """The pinned dependencies (and the build backend) as wheels for the image's Python,
    downloaded on the host once per set of pins. Kept in the cache, keyed by the pins."""
    build_requires = _build_requires()
    key = wheelhouse_key()
    folder = cache_dir() / "wheelhouse" / key
    if (folder / "requirements.txt").is_file():
        return folder
    started = time.monotonic()
    say(f"downloading the pinned dependencies as wheels for Python {TARGET_PYTHON} into {folder} ...")
    partial = folder.with_name(key + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    platforms = [argument for tag in _platform_tags() for argument in ("--platform", tag)]
    _run([sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check", "--only-binary=:all:",
          "--python-version", TARGET_PYTHON, "--implementation", "cp", "--abi", f"cp{TARGET_PYTHON.replace('.', '')}",
          "--abi", "abi3", "--abi", "none", *platforms, "-d", str(partial), *requirements(), *build_requires],
         timeout=1800)
    (partial / "requirements.txt").write_text("\n".join(requirements()) + "\n")
    shutil.rmtree(folder, ignore_errors=True)
    partial.rename(folder)
    say(f"wheelhouse ready in {time.monotonic() - started:.0f} s")
    return folder


def build_deps(engine: Engine, base: str, wheels: Path) -> str:
    dockerfile = ROOT / "deploy" / "offline-deps.Dockerfile"
    tag = deps_tag()
    if engine.has_image(tag):
        return tag
    started = time.monotonic()
    say(f"building {tag}: the pinned dependencies on the base, from the wheelhouse (no network) ...")
    # --no-cache: the wheels come in through a bind mount, which the engine's layer cache
    # does not see, so a cached layer of other pins would be reused (it was: an image
    # tagged for new pins held the old ones). The image is built once per tag anyway.
    engine.run("build", "--no-cache", "--network", "none", "-f", str(dockerfile), "--build-arg", f"BASE={base}",
               "--build-arg", f"WHEELHOUSE={wheels.name}", "-t", tag, str(wheels), timeout=1800)
    say(f"{tag} built in {time.monotonic() - started:.0f} s")
    _drop_superseded(engine, "semservo-deps", keep=tag)
    return tag


def _drop_superseded(engine: Engine, repository: str, keep: str) -> None:
    """Earlier builds (other pins, other sources) are caches no longer used: removed
    when no container uses them."""
    listed = engine.run("images", "--format", "{{.Repository}}:{{.Tag}}", check=False).stdout.decode().split()
    for image in listed:
        if image.rpartition("/")[2].startswith(f"{repository}:") and image.rpartition("/")[2] != keep:
            engine.run("rmi", image, check=False)
    engine.run("image", "prune", "-f", "--filter", f"label={SOURCE_LABEL}", check=False)


def project_wheel(wheels: Path, out: Path) -> Path:
    """semservo's own wheel, built from a copy of its sources (nothing written into the
    checkout) with the build backend from the wheelhouse (no network)."""
    source = out / "src"
    for name in ("pyproject.toml", "README.md"):
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, source / name)
    for folder in ("shared", "services"):
        shutil.copytree(ROOT / folder, source / folder,
                        ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", "*.pyc"))
    _run([sys.executable, "-m", "pip", "wheel", "--quiet", "--disable-pip-version-check", "--no-deps", "--no-index",
          "--find-links", str(wheels), "-w", str(out), str(source)], timeout=600)
    shutil.rmtree(source)
    return next(out.glob("semservo-*.whl"))


def build_offline(engine: Engine) -> None:
    base = build_base(engine)
    wheels = wheelhouse()
    deps = build_deps(engine, base, wheels)
    key = offline_key()
    if (engine.image_labels(IMAGE) or {}).get(SOURCE_LABEL) == key:
        return
    started = time.monotonic()
    say(f"building {IMAGE} (offline: the project's wheel on {deps}) ...")
    with tempfile.TemporaryDirectory(prefix="semservo-app-") as folder:
        project_wheel(wheels, Path(folder))
        engine.run("build", "--network", "none", "-f", str(ROOT / "deploy" / "offline.Dockerfile"),
                   "--build-arg", f"DEPS={deps}", "--label", f"{SOURCE_LABEL}={key}", "-t", IMAGE, folder,
                   timeout=900)
    say(f"{IMAGE} built in {time.monotonic() - started:.0f} s")
    _drop_superseded(engine, "semservo", keep=IMAGE)


def build_online(engine: Engine) -> None:
    key = online_key()
    if (engine.image_labels(IMAGE) or {}).get(SOURCE_LABEL) == key:
        return
    started = time.monotonic()
    say(f"building {IMAGE} from deploy/Dockerfile (online: the registry's python image, PyPI) ...")
    engine.run("build", "-f", str(ROOT / "deploy" / "Dockerfile"), "--label", f"{SOURCE_LABEL}={key}",
               "-t", IMAGE, str(ROOT), timeout=1800)
    say(f"{IMAGE} built in {time.monotonic() - started:.0f} s")


def registry_answers(timeout_s: float = 5.0) -> bool:
    """Docker Hub's registry API answers (401 without a login is an answer)."""
    try:
        urllib.request.urlopen("https://registry-1.docker.io/v2/", timeout=timeout_s)
        return True
    except urllib.error.HTTPError:
        return True
    except (urllib.error.URLError, OSError, TimeoutError):
        return False


def build(engine: Engine, mode: str | None = None) -> str:
    """Build what is missing or out of date; returns the path taken (online/offline)."""
    mode = (mode or os.environ.get("SEMSERVO_BUILD") or "auto").lower()
    if mode not in ("auto", "online", "offline"):
        raise StackError(f"SEMSERVO_BUILD must be auto, online or offline, not {mode!r}")
    if mode == "auto":
        built_from = (engine.image_labels(IMAGE) or {}).get(SOURCE_LABEL)
        if built_from == offline_key():
            return "offline, up to date"
        if built_from == online_key():
            return "online, up to date"
        mode = "online" if registry_answers() else "offline"
        say(f"{IMAGE} is {'missing' if built_from is None else 'out of date'}: building it {mode} "
            f"({'a registry answers' if mode == 'online' else 'no registry answers'})")
    if mode == "online":
        try:
            build_online(engine)
            return "online"
        except StackError as error:
            if os.environ.get("SEMSERVO_BUILD", "auto").lower() == "online":
                raise
            say(f"the online build failed ({str(error)[-300:]}); building offline instead")
    build_offline(engine)
    return "offline"


# -- the stack ----------------------------------------------------------------------------
@dataclass
class Stack:
    """One compose project of docker-compose.yml: its engine, name, keys, token, URL."""

    engine: Engine
    project: str = field(default_factory=lambda: os.environ.get("SEMSERVO_COMPOSE_PROJECT", "semservo"))
    folder: Path | None = None
    http_publish: str = field(default_factory=lambda: os.environ.get("SEMSERVO_HTTP_PUBLISH", "8000"))

    def __post_init__(self) -> None:
        if self.folder is None:
            self.folder = Path(os.environ.get("SEMSERVO_COMPOSE_DIR") or ROOT / ".compose" / self.project)
        self.folder = Path(self.folder).resolve()

    # names
    @property
    def keys_dir(self) -> Path:
        return self.folder / "keys"

    @property
    def token_file(self) -> Path:
        return self.folder / "token"

    @property
    def token(self) -> str:
        return self.token_file.read_text().strip()

    @property
    def url(self) -> str:
        host, _, port = self.http_publish.rpartition(":")
        host = host.strip("[]") or "127.0.0.1"
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '::') else host}:{port}"

    def container(self, service: str) -> str:
        return f"{self.project}-{service}-1"

    def _named(self, kind: str, name: str) -> str:
        """The engine's name of this project's network or volume NAME: compose prefixes
        the project with "_", podman-compose (Docker's names asked for) with "-"."""
        listed = self.engine.run(kind, "ls", "--filter", f"label=com.docker.compose.project={self.project}",
                                 "--format", "{{.Name}}", check=False).stdout.decode().split()
        for found in listed:
            if found in (f"{self.project}_{name}", f"{self.project}-{name}"):
                return found
        return f"{self.project}_{name}"

    def network(self, name: str) -> str:
        return self._named("network", name)

    @property
    def volume(self) -> str:
        return self._named("volume", "runs")

    # compose
    def compose_env(self) -> dict[str, str]:
        env = self.engine.env
        env.update(SEMSERVO_KEYS_DIR=str(self.keys_dir), SEMSERVO_HTTP_PUBLISH=self.http_publish)
        env["SEMSERVO_API_TOKEN"] = self.token if self.token_file.is_file() else "unset"
        return env

    def compose(self, *args: str, check: bool = True, timeout: float | None = 600,
                capture: bool = True) -> subprocess.CompletedProcess:
        log = self.folder / "compose.log"
        self.folder.mkdir(parents=True, exist_ok=True)
        result = _run([*self.engine.compose_command(self.project), *args], env=self.compose_env(), check=False,
                      timeout=timeout, capture=capture)
        if capture:
            with log.open("ab") as out:
                out.write(f"$ compose {' '.join(args)}\n".encode() + (result.stdout or b"") + (result.stderr or b""))
        if check and result.returncode != 0:
            raise StackError(f"compose {' '.join(args)} failed ({result.returncode}); its output is in {log}:\n"
                             + ((result.stderr or b"") + (result.stdout or b"")).decode(errors="replace")[-1500:])
        return result

    def containers(self) -> dict[str, dict]:
        """This project's containers by service: state, pid, restart count, health."""
        listed = self.engine.run("ps", "-a", "-q", "--filter", f"label=com.docker.compose.project={self.project}",
                                 check=False)
        ids = listed.stdout.decode().split()
        if not ids:
            return {}
        found = {}
        for info in json.loads(self.engine.run("inspect", *ids).stdout):
            labels = info.get("Config", {}).get("Labels") or {}
            service = labels.get("com.docker.compose.service")
            state = info.get("State", {})
            health = state.get("Health") or state.get("Healthcheck") or {}
            found[service] = {"id": info.get("Id"), "name": info.get("Name", "").lstrip("/"),
                              "status": state.get("Status"),
                              "image": str(info.get("Image", "")).removeprefix("sha256:"),
                              "running": state.get("Running"), "pid": state.get("Pid"),
                              "restarts": info.get("RestartCount", 0), "health": health.get("Status")}
        return found

    def running(self) -> bool:
        present = self.containers()
        return bool(present) and all(present.get(name, {}).get("running") for name in SERVICES)

    # keys and token
    def _remove_tree(self, path: Path) -> None:
        if not path.exists():
            return
        if os.geteuid() == 0:
            shutil.rmtree(path)
        else:  # owned by the container's user: removed from inside a container
            self.engine.run("run", "--rm", "--user", "0", "--network", "none", "-v", f"{path.parent}:/parent",
                            IMAGE, "rm", "-rf", f"/parent/{path.name}")

    def fresh_credentials(self) -> None:
        """New CURVE keys (semservo keys), readable by the containers' user, and a new token."""
        self.folder.mkdir(parents=True, exist_ok=True)
        self._remove_tree(self.keys_dir)
        semservo = Path(sys.executable).parent / "semservo"
        _run([str(semservo) if semservo.exists() else "semservo", "keys", str(self.keys_dir)])
        if os.geteuid() == 0:
            for path in [self.keys_dir, *self.keys_dir.rglob("*")]:
                os.chown(path, CONTAINER_UID, CONTAINER_UID)
        else:
            self.engine.run("run", "--rm", "--user", "0", "--network", "none", "-v", f"{self.keys_dir}:/keys",
                            IMAGE, "chown", "-R", f"{CONTAINER_UID}:{CONTAINER_UID}", "/keys")
        self.token_file.write_text(secrets.token_urlsafe(24) + "\n")
        self.token_file.chmod(0o600)

    # health
    def check(self, service: str) -> tuple[bool, str]:
        """Run the service's own health command now (its compose healthcheck). Podman
        records the result (``podman healthcheck run``: without systemd nothing else
        runs it); Docker runs its healthchecks itself, so the command runs by exec."""
        name = self.container(service)
        if self.engine.name == "podman":
            result = self.engine.run("healthcheck", "run", name, check=False, timeout=60)
        else:
            test = json.loads(self.engine.run("inspect", "--format", "{{json .Config.Healthcheck.Test}}", name,
                                              check=False).stdout or b"null") or ["CMD", "semservo", "health", service]
            command = test[1:] if test[0] == "CMD" else ["sh", "-c", test[1]]
            result = self.engine.run("exec", name, *command, check=False, timeout=60)
        output = ((result.stdout or b"") + (result.stderr or b"")).decode(errors="replace").strip()
        return result.returncode == 0, output

    def health(self) -> dict[str, tuple[bool, str]]:
        with concurrent.futures.ThreadPoolExecutor(len(SERVICES)) as pool:
            return dict(zip(SERVICES, pool.map(self.check, SERVICES)))

    def wait_healthy(self, timeout_s: float = 180.0, services: tuple[str, ...] = SERVICES) -> dict[str, float]:
        """Run each service's health command, in rounds, until every one succeeds; the
        seconds each took. Each check starts a process in its container: a few at a
        time, with a pause between rounds, so waiting does not slow the start it waits for."""
        started = time.monotonic()
        healthy: dict[str, float] = {}
        last: dict[str, str] = {}
        with concurrent.futures.ThreadPoolExecutor(3) as pool:
            while True:
                pending = [service for service in services if service not in healthy]
                for service, (ok, output) in zip(pending, pool.map(self.check, pending)):
                    if ok:
                        healthy[service] = time.monotonic() - started
                    else:
                        last[service] = output
                pending = [service for service in services if service not in healthy]
                if not pending:
                    return healthy
                if time.monotonic() - started > timeout_s:
                    raise StackError("not healthy after {:.0f} s: {} (logs: ./dev compose logs SERVICE)".format(
                        timeout_s, "; ".join(f"{service}: {last.get(service) or 'no answer'}" for service in pending)))
                time.sleep(2.0)

    def wait_gateway_sees_all(self, timeout_s: float = 180.0) -> None:
        """Until the gateway answers and reports every service up and a frame: it asks
        them over ZeroMQ anyway, so waiting on it starts no process in any container
        (each health command is a Python start; on 2 busy cores, dozens of them slow the
        very start they wait for)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            status = self._gateway_status() or {}
            services = status.get("services") or {}
            if status.get("latest_frame_seq") is not None and services and \
                    all(service.get("up") for service in services.values()):
                return
            time.sleep(0.5)

    def _gateway_status(self) -> dict | None:
        """The gateway's GET /status, or None while it does not answer (yet)."""
        try:
            with urllib.request.urlopen(f"{self.url}/status", timeout=5) as response:
                return json.load(response)
        except (urllib.error.URLError, OSError, ValueError):
            return None

    def wait_frames(self, timeout_s: float = 60.0) -> None:
        """Until the gateway has a frame: the image server's frames crossed to PC 2."""
        deadline = time.monotonic() + timeout_s
        while True:
            if (self._gateway_status() or {}).get("latest_frame_seq") is not None:
                return
            if time.monotonic() > deadline:
                raise StackError(f"no frame reached the gateway at {self.url} within {timeout_s:.0f} s")
            time.sleep(0.5)

    # lifecycle
    def image_id(self) -> str | None:
        result = self.engine.run("image", "inspect", "--format", "{{.Id}}", IMAGE, check=False)
        return result.stdout.decode().strip().removeprefix("sha256:") or None if result.returncode == 0 else None

    def _configuration(self) -> str:
        """What the running containers were made from: the compose file and the port."""
        return _digest(COMPOSE_FILE.read_bytes(), self.http_publish)

    def up(self, *, build_mode: str | None = None, timeout_s: float = 180.0) -> dict:
        """Build what is missing, start the stack with fresh keys and token (unless it is
        up already, from this image and this compose file), wait until every service is
        healthy and frames reach the gateway."""
        timings: dict[str, float | str] = {}
        started = time.monotonic()
        timings["build_path"] = build(self.engine, build_mode)
        timings["build_s"] = time.monotonic() - started
        state_file = self.folder / "stack.json"
        saved = json.loads(state_file.read_text()) if state_file.is_file() else {}
        present = self.containers()
        current = self.running() and saved.get("configuration") == self._configuration() and \
            {info["image"] for info in present.values()} == {self.image_id()}
        if current:
            say(f"project {self.project} is up already, from this image and compose file")
        else:
            if present:  # stopped, half up, or made from an older image or compose file: start over
                say(f"project {self.project} has containers from before: replacing them")
                self.compose("down", "--remove-orphans")
            self.fresh_credentials()
            started = time.monotonic()
            self.compose("up", "-d", "--no-build", "--remove-orphans")
            timings["create_s"] = time.monotonic() - started
        started = time.monotonic()
        self.wait_gateway_sees_all(timeout_s)  # then each health command, once if all is well
        timings["healthy_s"] = max(self.wait_healthy(max(timeout_s - (time.monotonic() - started), 30)).values())
        self.wait_frames()
        timings["frames_s"] = time.monotonic() - started
        state = {"engine": self.engine.name, "project": self.project, "url": self.url,
                 "token_file": str(self.token_file), "keys_dir": str(self.keys_dir),
                 "configuration": self._configuration(), "timings": timings}
        state_file.write_text(json.dumps(state, indent=2) + "\n")
        return state

    def down(self, *, volumes: bool = False) -> None:
        self.compose("down", "--remove-orphans", *(["--volumes"] if volumes else []), timeout=300)
        if volumes and self.engine.run("volume", "exists" if self.engine.name == "podman" else "inspect",
                                       self.volume, check=False).returncode == 0:
            self.engine.run("volume", "rm", self.volume)


# -- the command line ----------------------------------------------------------------------
def _print_up(stack: Stack, state: dict) -> None:
    timings = state["timings"]
    started = f"started in {timings['create_s']:.0f} s, " if "create_s" in timings else ""
    print(f"semservo is up as containers ({stack.engine.name}, project {stack.project}): image {IMAGE} "
          f"({timings['build_path']}) ready in {timings['build_s']:.0f} s, {started}every service healthy and "
          f"frames at the gateway {timings['frames_s']:.0f} s later")
    print(f"  gateway      {stack.url}    (dashboard {stack.url}/ , API {stack.url}/docs)")
    print(f"  token        {stack.token_file}    (export SEMSERVO_API_TOKEN=$(cat {stack.token_file}))")
    print(f"  CURVE keys   {stack.keys_dir}")
    print(f"  lab script   python -c \"from semservo.client import Client; "
          f"print(Client('{stack.url}', token=open('{stack.token_file}').read().strip()).status())\"")
    print("  health       ./dev compose health      stop: ./dev compose down")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="./dev compose", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 1)[1])
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    up = commands.add_parser("up", help="build what is missing, start on fake hardware, wait until healthy")
    up.add_argument("--offline", dest="build", action="store_const", const="offline", help="build offline")
    up.add_argument("--online", dest="build", action="store_const", const="online", help="build online")
    up.add_argument("--timeout", type=float, default=180.0, help="seconds to wait for health (default 180)")
    down = commands.add_parser("down", help="stop and remove the containers (records stay on the volume)")
    down.add_argument("--volumes", action="store_true", help="remove the records volume too")
    commands.add_parser("health", help="run every service's health command now")
    build_command = commands.add_parser("build", help="build the image only")
    build_command.add_argument("--offline", dest="build", action="store_const", const="offline")
    build_command.add_argument("--online", dest="build", action="store_const", const="online")
    for name in ("ps", "logs"):
        passthrough = commands.add_parser(name, help=f"compose {name} for this project")
        passthrough.add_argument("args", nargs=argparse.REMAINDER)
    args = parser.parse_args(argv)
    try:
        engine = detect_engine()
        stack = Stack(engine)
        if args.command == "up":
            _print_up(stack, stack.up(build_mode=args.build, timeout_s=args.timeout))
        elif args.command == "down":
            stack.down(volumes=args.volumes)
            print(f"project {stack.project} is down" + (" and its records volume removed" if args.volumes else
                                                        f" (records kept on the volume {stack.volume})"))
        elif args.command == "health":
            if not stack.containers():
                print(f"project {stack.project} is not up (./dev compose up)")
                return 1
            results = stack.health()
            for service, (ok, output) in results.items():
                print(f"{service:<12} {'healthy' if ok else 'UNHEALTHY':<10} {output.splitlines()[-1] if output else ''}")
            return 0 if all(ok for ok, _ in results.values()) else 1
        elif args.command == "build":
            print(f"{IMAGE} ready ({build(engine, args.build)})")
        else:
            return stack.compose(args.command, *args.args, capture=False, check=False, timeout=None).returncode
    except StackError as error:
        print(f"compose: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
