"""The simulated SEM saving its frames to a folder, as an SEM's own software does.

With ``fakelab.save_frames_dir`` set, the fake lab scans continuously and saves every
frame there as a Thermo Fisher/FEI-style TIFF: the image with a data bar under it and
the acquisition in an FEI metadata tag (pixel width, dwell, high voltage, working
distance, detector, the image area's height). Each file is written slowly, in chunks,
as a real instrument's software writes over a network share, so whatever watches the
folder must wait for complete files. This is what the image server's ``watch`` source
is tested against, end to end.
"""

from __future__ import annotations

import io
import logging
import threading
import time
from pathlib import Path

import numpy as np
import tifffile

from semservo.messages import ScanRequest
from semservo.sem_metadata import FEI_TAGS
from semservo.simulation.world import World
from services.fakelab.scan import scan_settings

log = logging.getLogger("fakelab.acquisition")

#: The data bar under each saved image, as a fraction of its height.
DATA_BAR_FRACTION = 0.125


def fei_metadata_text(*, pixel_size_nm: float, dwell_ns: float, working_distance_mm: float, rows: int,
                      cols: int, high_voltage_kv: float = 5.0, detector: str = "ETD") -> str:
    """The ``[Section] Key=value`` text Thermo Fisher/FEI instruments store (SI units)."""
    return "\r\n".join([
        "[System]", "SystemType=semservo fake lab",
        "[Beam]", f"HV={high_voltage_kv * 1e3:g}",
        "[Scan]", f"PixelWidth={pixel_size_nm * 1e-9:.6e}", f"PixelHeight={pixel_size_nm * 1e-9:.6e}",
        f"Dwelltime={dwell_ns * 1e-9:.6e}",
        "[Stage]", f"WorkingDistance={working_distance_mm * 1e-3:.6e}",
        "[Detectors]", f"Name={detector}",
        "[Image]", f"ResolutionX={cols}", f"ResolutionY={rows}", "",
    ])


def with_data_bar(pixels: np.ndarray) -> np.ndarray:
    """The image with a black data bar under it: white blocks for text and a scale bar."""
    rows, cols = pixels.shape
    bar = np.zeros((max(8, int(rows * DATA_BAR_FRACTION)), cols), dtype=pixels.dtype)
    white = np.iinfo(pixels.dtype).max
    height = bar.shape[0]
    bar[height // 3: height // 3 + 3, cols // 20: cols // 4] = white  # the scale bar
    for start in range(cols // 3, cols - 10, 14):  # "text"
        bar[height // 4: 3 * height // 4, start: start + 8: 2] = white
    return np.vstack([pixels, bar])


def encode_fei_tiff(pixels: np.ndarray, metadata_text: str) -> bytes:
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, pixels, extratags=[(FEI_TAGS[1], "s", 0, metadata_text, True)], metadata=None)
    return buffer.getvalue()


class FolderWriter:
    """Scans the world continuously and saves each frame to ``folder`` in ``chunks``
    writes, ``chunk_pause_s`` apart, a frame every ``interval_s`` at most (wall time; in
    a thread of its own). It keeps the last ``keep`` frames it saved and deletes its own
    older ones (an SEM's autosave folder would grow by gigabytes an hour); None keeps all."""

    def __init__(self, world: World, folder: Path, *, chunks: int = 4, chunk_pause_s: float = 0.01,
                 interval_s: float = 0.1, request: ScanRequest | None = None, counters=None, keep: int | None = 200):
        self.world = world
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.chunks = max(1, chunks)
        self.chunk_pause_s = chunk_pause_s
        self.interval_s = interval_s
        self.request = request or ScanRequest()
        self.counters = counters if counters is not None else {}
        self.saved = 0
        self.keep = keep
        self.deleted = 0
        self.last_error: str | None = None
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="save-frames", daemon=True)

    def start(self) -> "FolderWriter":
        self.thread.start()
        log.info("saving every frame to %s as an SEM's software would", self.folder)
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            started = time.monotonic()
            try:
                self.save_one()
                self._stop.wait(max(0.0, self.interval_s - (time.monotonic() - started)))
            except Exception as error:  # noqa: BLE001 - keep saving; say why one failed
                self.last_error = f"saving a frame failed: {type(error).__name__}: {error}"
                log.exception("saving a frame failed")
                self._stop.wait(1.0)

    def save_one(self) -> Path:
        settings = scan_settings(self.world, self.request)
        pixels, _, _ = self.world.scan(settings)
        text = fei_metadata_text(pixel_size_nm=settings.pixel_um * 1000, dwell_ns=settings.dwell_ns,
                                 working_distance_mm=self.world.preset.working_distance_mm + settings.working_distance_um / 1000,
                                 rows=pixels.shape[0],
                                 cols=pixels.shape[1])
        data = encode_fei_tiff(with_data_bar(pixels), text)
        path = self.folder / f"frame{self.saved:06d}.tif"
        step = -(-len(data) // self.chunks)
        with open(path, "wb") as file:
            for start in range(0, len(data), step):
                file.write(data[start: start + step])
                file.flush()
                if start + step < len(data) and self._stop.wait(self.chunk_pause_s):
                    break
        self.saved += 1
        self.counters["frames_saved"] = self.saved
        if self.keep is not None and self.saved > self.keep:
            # Its own oldest frame only (files it did not write are not its to delete).
            (self.folder / f"frame{self.saved - self.keep - 1:06d}.tif").unlink(missing_ok=True)
            self.deleted += 1
            self.counters["frames_deleted"] = self.deleted
        return path

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=10)
