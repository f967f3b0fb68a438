"""Connecting to a microscope through OpenFIBSEM, once per process and address.

``openfibsem://MANUFACTURER@HOST`` names one (``openfibsem://Demo@localhost``,
``openfibsem://Thermo@10.0.0.1``, ``openfibsem://Tescan@192.168.0.5``), with options
after ``?``: ``beam`` (``electron``, default, or ``ion``), ``config`` (a fibsem
microscope-configuration YAML), ``stage_move`` (``stable``, default: fibsem's
``stable_move``, corrected for the pre-tilt; ``relative``: ``move_stage_relative`` on x
and y), ``beam_limit_um`` (the beam shift's travel where the SDK does not report one),
``stage_signs`` / ``beam_signs`` (:mod:`semservo.openfibsem.units`).
"""

from __future__ import annotations

import atexit
import logging
import os
import shutil
import tempfile
import threading
from dataclasses import dataclass, field
from urllib.parse import parse_qs, urlsplit

INSTALL_HINT = "OpenFIBSEM is not installed: pip install -e '.[openfibsem]' (the semservo[openfibsem] extra)"

#: Where the beam shift may go when the microscope's SDK does not say (TESCAN, the demo):
#: +-10 um, a conservative beam shift at SEM working distances. Set it from your
#: microscope's manual (the URL's ``beam_limit_um``).
DEFAULT_BEAM_LIMIT_UM = 10.0


def require_fibsem():
    """The ``fibsem`` package, or an ImportError that says how to install it."""
    try:
        import fibsem  # noqa: F401
        import fibsem.structures
    except ImportError as error:
        raise ImportError(f"{INSTALL_HINT} ({error})") from None
    quiet_fibsem_logs()
    return fibsem


class _FibsemChatter(logging.Filter):
    """fibsem logs through the root logger (``logging.info``): its info lines (one per
    image acquired) would drown a service's log. Its warnings and errors pass."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.WARNING or f"{os.sep}fibsem{os.sep}" not in record.pathname


def quiet_fibsem_logs() -> None:
    """Keep fibsem's warnings and errors in the log, not its info lines (once)."""
    root = logging.getLogger()
    if not any(isinstance(existing, _FibsemChatter) for existing in root.filters):
        root.addFilter(_FibsemChatter())


@dataclass(frozen=True)
class Address:
    """Which microscope, and how semservo drives it (parsed from an ``openfibsem://`` URL)."""

    manufacturer: str = "Demo"
    host: str = "localhost"
    options: dict[str, str] = field(default_factory=dict)

    @classmethod
    def parse(cls, url: str) -> "Address":
        parts = urlsplit(url)
        if parts.scheme != "openfibsem" or not parts.netloc:
            raise ValueError(f"an OpenFIBSEM microscope is named openfibsem://MANUFACTURER@HOST (e.g. "
                             f"openfibsem://Demo@localhost), got {url!r}")
        manufacturer, _, host = parts.netloc.rpartition("@")
        options = {key: values[-1] for key, values in parse_qs(parts.query).items()}
        known = {"beam", "config", "stage_move", "beam_limit_um", "stage_signs", "beam_signs"}
        unknown = set(options) - known
        if unknown:
            raise ValueError(f"unknown option(s) {', '.join(sorted(unknown))} in {url!r}; known: {', '.join(sorted(known))}")
        return cls(manufacturer or "Demo", host or "localhost", options)


_microscopes: dict[tuple[str, str, str | None], object] = {}
_lock = threading.Lock()


def connect(manufacturer: str = "Demo", host: str = "localhost", config: str | None = None):
    """The microscope at ``host`` (fibsem's ``setup_session``), connected once per process:
    the image source and the motion driver of one process share it. The session's
    folder is a temporary one (fibsem's default lies inside its installed package),
    removed when the process exits."""
    require_fibsem()
    from fibsem import utils

    key = (manufacturer.lower(), host, config)
    with _lock:
        if key not in _microscopes:
            session = tempfile.mkdtemp(prefix="semservo-openfibsem-")
            atexit.register(shutil.rmtree, session, ignore_errors=True)
            microscope, _settings = utils.setup_session(session_path=session, config_path=config,
                                                        manufacturer=manufacturer, ip_address=host,
                                                        setup_logging=False)
            if type(microscope).__name__ == "DemoMicroscope":
                at_working_height(microscope)
            _microscopes[key] = microscope
        return _microscopes[key]


#: Where a DemoMicroscope's stage is put (m): its z starts at 0, the floor of its range,
#: where no stable move with a y component may go (it moves z down); a real stage sits
#: near the working distance.
DEMO_WORKING_HEIGHT_M = 4e-3


def at_working_height(microscope) -> None:
    """Raise a DemoMicroscope's stage from z = 0 (the floor of its range) to
    :data:`DEMO_WORKING_HEIGHT_M`, as a microscope's stage sits, so stable moves can go
    both ways. Only for a demo that has not moved yet."""
    from fibsem.structures import FibsemStagePosition

    position = microscope.get_stage_position()
    if float(position.z or 0.0) == 0.0:
        microscope.move_stage_absolute(FibsemStagePosition(z=DEMO_WORKING_HEIGHT_M))


def beam_type(name: str | None):
    """fibsem's BeamType for ``electron`` (default) or ``ion``."""
    require_fibsem()
    from fibsem.structures import BeamType

    text = (name or "electron").strip().lower()
    if text not in ("electron", "ion"):
        raise ValueError(f"beam must be electron or ion, got {name!r}")
    return BeamType.ELECTRON if text == "electron" else BeamType.ION
