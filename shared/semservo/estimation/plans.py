"""FFT plans (FFTW through pyFFTW), made once per shape and kept as wisdom between runs.
"""

from __future__ import annotations

import logging
import os
import pickle
import threading
from dataclasses import dataclass
from pathlib import Path

import pyfftw

log = logging.getLogger(__name__)


def wisdom_path() -> Path:
    """Where FFTW wisdom is kept between runs (``SEMSERVO_FFTW_WISDOM`` overrides)."""
    default = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "semservo" / "fftw-wisdom.pickle"
    return Path(os.environ.get("SEMSERVO_FFTW_WISDOM", default))


#: Held around every plan made and all wisdom read or written, in this process: FFTW
#: allows only the execution of plans to run concurrently, and pyFFTW takes its own lock
#: for planning but not for exporting wisdom (an estimator made in a thread, for a
#: partial frame's rows, must not plan while another exports).
PLANNING_LOCK = threading.RLock()
#: The wisdom files already read into this process (the setting may name another later).
_wisdom_loaded: set[Path] = set()


def _load_wisdom(path: Path) -> None:
    with PLANNING_LOCK:
        if path in _wisdom_loaded:
            return
        _wisdom_loaded.add(path)
        try:
            pyfftw.import_wisdom(pickle.loads(path.read_bytes()))
        except (OSError, pickle.UnpicklingError, EOFError, ValueError, TypeError):
            log.debug("no FFTW wisdom at %s yet: plans are measured once and saved", path)


def _save_wisdom(path: Path) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
        temporary.write_bytes(pickle.dumps(pyfftw.export_wisdom()))
        temporary.replace(path)
    except OSError as error:
        log.debug("could not save FFTW wisdom to %s: %s", path, error)


@dataclass
class FFTPlans:
    """Real-input forward and inverse 2-D FFTs of one shape, planned once (FFTW)."""

    forward: pyfftw.FFTW
    inverse: pyfftw.FFTW

    @classmethod
    def for_shape(cls, shape: tuple[int, int], effort: str = "FFTW_MEASURE", threads: int = 1) -> "FFTPlans":
        path = wisdom_path()
        with PLANNING_LOCK:
            _load_wisdom(path)
            before = pyfftw.export_wisdom()
            real = pyfftw.empty_aligned(shape, dtype="float32")
            spectrum = pyfftw.empty_aligned((shape[0], shape[1] // 2 + 1), dtype="complex64")
            plans = cls(
                forward=pyfftw.FFTW(real, spectrum, axes=(0, 1), direction="FFTW_FORWARD", flags=(effort,),
                                    threads=threads),
                inverse=pyfftw.FFTW(spectrum.copy(), real.copy(), axes=(0, 1), direction="FFTW_BACKWARD",
                                    flags=(effort, "FFTW_DESTROY_INPUT"), threads=threads),
            )
            # Saved when planning learned something, and also when this file lacks what the
            # process already knew (plans made earlier, under another wisdom path).
            if pyfftw.export_wisdom() != before or not path.is_file():
                _save_wisdom(path)
        return plans
