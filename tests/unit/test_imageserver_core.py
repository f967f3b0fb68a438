"""The image server's replay source and pacing core, without sockets."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from semservo.config import pixel_size_nm
from semservo.imagefiles import ImageFileError, write_image
from services.imageserver.core import ImageServerCore, Pacer
from services.imageserver.sources import ReplaySource


def test_replays_the_real_recording_in_name_order(recorded_run):
    source = ReplaySource(recorded_run, pattern="frame*", loop=False)
    labels, first_pixels = [], None
    while (image := source.acquire()) is not None:
        labels.append(image.label)
        first_pixels = first_pixels if first_pixels is not None else image.pixels
    assert labels == [f"frame{i:02d}.png" for i in range(54)]
    expected = np.asarray(Image.open(recorded_run / "frame00.png"))
    np.testing.assert_array_equal(first_pixels, expected)
    assert first_pixels.shape == (512, 512) and first_pixels.dtype == np.uint8
    assert not first_pixels.flags.writeable  # published zero-copy, so frozen


def test_the_recording_is_replayed_without_its_taught_image_unless_a_pattern_asks_for_it(recorded_run):
    """The 2013 run keeps its taught image, reference.png, beside frame00-53: not a frame
    of the run (replayed, the view jumped to the taught pose after the last frame)."""
    source = ReplaySource(recorded_run)
    assert len(source.paths) == 54 and source.paths[-1].name == "frame53.png"
    assert source.describe()["left_out"] == ["reference.png"]
    every = ReplaySource(recorded_run, pattern="*")
    assert len(every.paths) == 55 and every.paths[-1].name == "reference.png" and "left_out" not in every.describe()


def test_loop_starts_again_and_once_stops(tmp_path):
    for index in range(3):
        write_image(tmp_path / f"f{index}.png", np.full((64, 64), index, np.uint16))
    looping = ReplaySource(tmp_path, loop=True)
    assert [looping.acquire().pixels[0, 0] for _ in range(7)] == [0, 1, 2, 0, 1, 2, 0]
    assert looping.passes == 2
    once = ReplaySource(tmp_path, loop=False)
    assert [once.acquire().pixels[0, 0] for _ in range(3)] == [0, 1, 2]
    assert once.acquire() is None


def test_metadata_precedence_command_line_then_file_then_settings(tmp_path):
    write_image(tmp_path / "a.tif", np.zeros((64, 128), np.uint8), magnification=5000, dwell_ns=360)
    from_file = ReplaySource(tmp_path).acquire()
    assert (from_file.magnification, from_file.dwell_ns) == (5000, 360)
    # The file's magnification says nothing of its microscope's screen: no pixel size is made up.
    assert from_file.pixel_size_nm is None

    overridden = ReplaySource(tmp_path, overrides={"magnification": 1200, "dwell_ns": 180}).acquire()
    assert (overridden.magnification, overridden.dwell_ns) == (1200, 180)
    assert overridden.pixel_size_nm == pytest.approx(pixel_size_nm(1200, width_px=128))  # the user's G: eq. 43

    explicit = ReplaySource(tmp_path, overrides={"pixel_size_nm": 10.0}).acquire()
    assert explicit.pixel_size_nm == 10.0

    Image.fromarray(np.zeros((64, 64), np.uint8)).save(tmp_path / "b.png")
    unknown = ReplaySource(tmp_path, pattern="b.png").acquire()
    assert (unknown.magnification, unknown.dwell_ns, unknown.pixel_size_nm) == (None, None, None)
    assert unknown.acquisition() == {}
    plain = ReplaySource(tmp_path, pattern="b.png", fallbacks={"magnification": 800, "dwell_ns": 999}).acquire()
    assert (plain.magnification, plain.dwell_ns) == (800, 999)
    assert plain.pixel_size_nm == pytest.approx(pixel_size_nm(800, width_px=64))
    # The settings fill only what the file does not say.
    assert ReplaySource(tmp_path, pattern="a.tif", fallbacks={"magnification": 800}).acquire().magnification == 5000


def test_bad_folders_fail_at_start_naming_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="no PNG or TIFF"):
        ReplaySource(tmp_path)
    write_image(tmp_path / "a.png", np.zeros((64, 64), np.uint8))
    write_image(tmp_path / "b.png", np.zeros((32, 64), np.uint8))
    with pytest.raises(ImageFileError, match="b.png"):
        ReplaySource(tmp_path)
    (tmp_path / "b.png").write_bytes(b"garbage")
    with pytest.raises(ImageFileError, match="b.png"):
        ReplaySource(tmp_path)


def test_pacer_keeps_rate_without_drift_and_without_bursts():
    pacer = Pacer(fps=10)
    assert pacer.seconds_until_due(0.0) == 0.0
    pacer.advance(0.0)
    pacer.advance(0.1003)  # a little late: the schedule keeps its grid
    assert pacer.next_due == pytest.approx(0.2)
    pacer.advance(5.0)  # a long stall: resume from now, do not burst to catch up
    assert pacer.next_due == pytest.approx(5.1)
    assert pacer.seconds_until_due(5.05) == pytest.approx(0.05)


def test_core_numbers_frames_and_reports_exhaustion(tmp_path):
    for index in range(2):
        write_image(tmp_path / f"f{index}.png", np.full((64, 64), index, np.uint8))
    core = ImageServerCore(ReplaySource(tmp_path, loop=False), fps=10)
    seq, image = core.next_frame(now=0.0)
    assert seq == 0 and image.pixels[0, 0] == 0
    assert core.next_frame(now=0.05) is None  # not due yet
    assert core.seconds_until_due(now=0.05) == pytest.approx(0.05)
    seq, image = core.next_frame(now=0.1)
    assert seq == 1 and image.pixels[0, 0] == 1
    assert core.next_frame(now=0.2) is None
    assert core.exhausted and core.seconds_until_due() is None


def test_core_refuses_bad_rates(tmp_path):
    write_image(tmp_path / "f.png", np.zeros((64, 64), np.uint8))
    with pytest.raises(ValueError):
        ImageServerCore(ReplaySource(tmp_path), fps=0)
    core = ImageServerCore(ReplaySource(tmp_path), fps=5)
    for bad in (0, -3, 1e9):
        with pytest.raises(ValueError):
            core.set_fps(bad)
    core.set_fps(25)
    assert core.pacer.fps == 25


def test_a_background_source_keeps_the_service_responsive_and_delivers_frames(tmp_path):
    """A source that blocks for longer than a health request may wait (a scan) runs in
    its own thread: acquire() never blocks, and every frame still arrives."""
    import time

    from services.imageserver.sources import BackgroundAcquisition, NotReady

    class SlowScanner:
        name = "slow"

        def __init__(self):
            self.count = 0

        def acquire(self, cancelled=None):
            time.sleep(0.2)  # a frame time
            self.count += 1
            from services.imageserver.sources import AcquiredImage

            return AcquiredImage(pixels=np.full((64, 64), self.count, np.uint8), acquired_at_ns=time.time_ns(),
                                 pixel_size_nm=100.0, magnification=1000.0, dwell_ns=720.0)

        def describe(self):
            return {"source": self.name}

    import threading

    ready = threading.Event()
    source = BackgroundAcquisition(SlowScanner(), fps=50, notify=ready.set)
    core = ImageServerCore(source, fps=50)
    try:
        started = time.monotonic()
        with pytest.raises(NotReady):
            source.acquire()
        assert time.monotonic() - started < 0.05  # never blocks
        frames, wake_ups = [], 0
        deadline = time.monotonic() + 3
        while len(frames) < 3 and time.monotonic() < deadline:
            due = core.next_frame()
            if due is None:
                if core.waiting_for_source:
                    # Nothing to do until the source says it has a frame: no polling.
                    assert core.seconds_until_due() is None
                    assert ready.wait(1.0), "the source tells when a frame is ready"
                    ready.clear()
                    wake_ups += 1
                else:
                    time.sleep(core.seconds_until_due())
            else:
                frames.append(due)
        assert wake_ups <= 6, "woken by frames, not by a poll"
        assert [seq for seq, _ in frames] == [0, 1, 2]
        assert [int(image.pixels[0, 0]) for _, image in frames] == [1, 2, 3]
    finally:
        source.close()


def test_a_focus_sweep_scans_each_working_distance_in_the_background():
    import time as clock

    from semservo.instruments import AcquiredImage
    from services.imageserver.sweep import FocusSweeps, check_working_distances, decode_sweep

    scanned = []

    def scan(working_distance_um: float) -> AcquiredImage:
        scanned.append(working_distance_um)
        return AcquiredImage(pixels=np.full((8, 8), len(scanned), np.uint8), acquired_at_ns=100 * len(scanned) + 60,
                             scan_started_at_ns=100 * len(scanned), source_interval_s=(len(scanned), len(scanned) + 0.5),
                             pixel_size_nm=70.0)

    sweeps = FocusSweeps(scan)
    started = sweeps.start([-1.0, 0.0, 1.0])
    for _ in range(100):
        result = sweeps.result(started["sweep_id"])
        if result["state"] != "scanning":
            break
        clock.sleep(0.01)
    assert result["state"] == "done" and scanned == [-1.0, 0.0, 1.0]
    frames = decode_sweep(result)
    assert frames.shape == (3, 8, 8) and frames[2, 0, 0] == 3 and result["source_interval_s"] == [1, 3.5]
    assert result["frame_times_ns"] == [130, 230, 330]  # the middle of each frame's scan
    with pytest.raises(KeyError):
        sweeps.result("nope")
    for bad in ([0.0, 1.0], [0.0, 2.0, 1.0], [0.0, 1.0, 3.0], [0.0, float("nan"), 1.0], "0,1,2", [0, True, 2]):
        with pytest.raises(ValueError):
            check_working_distances(bad)
    sweeps.close()
