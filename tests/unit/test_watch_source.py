"""The ``watch`` source on a real folder, with real OS events (inotify here) and with
polling: a writer that saves slowly in chunks, garbage, deletions and renames."""

from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile

from semservo.instruments import NotReady
from services.fakelab.acquisition import encode_fei_tiff, fei_metadata_text, with_data_bar
from services.imageserver.watch import WatchSource


def frame(index: int, rows: int = 96, cols: int = 128) -> np.ndarray:
    return np.full((rows, cols), 10 + index, np.uint8) + np.arange(cols, dtype=np.uint8)[None, :] // 4


def fei_file(index: int) -> bytes:
    text = fei_metadata_text(pixel_size_nm=20.0, dwell_ns=500, working_distance_mm=5.0, rows=96, cols=128)
    return encode_fei_tiff(with_data_bar(frame(index)), text)


def slow_write(path: Path, data: bytes, chunks: int = 5, pause_s: float = 0.06) -> None:
    """As an SEM's software saving over a slow share: several writes, pauses between."""
    step = -(-len(data) // chunks)
    with open(path, "wb") as file:
        for start in range(0, len(data), step):
            file.write(data[start: start + step])
            file.flush()
            time.sleep(pause_s)


def collect(source: WatchSource, count: int, timeout_s: float = 20.0) -> list:
    images, deadline = [], time.monotonic() + timeout_s
    while len(images) < count and time.monotonic() < deadline:
        try:
            images.append(source.acquire())
        except NotReady:
            time.sleep(0.01)
    return images


def nothing_more(source: WatchSource, for_s: float = 1.5) -> bool:
    deadline = time.monotonic() + for_s
    while time.monotonic() < deadline:
        try:
            source.acquire()
            return False
        except NotReady:
            time.sleep(0.02)
    return True


@pytest.fixture(params=[False, True], ids=["os-events", "polling"])
def watched(request, tmp_path):
    source = WatchSource(tmp_path, settle_s=0.3, polling=request.param)
    yield tmp_path, source
    source.close()


def test_slowly_written_frames_come_once_each_in_order_whole_with_their_metadata(watched):
    folder, source = watched
    writer = threading.Thread(target=lambda: [slow_write(folder / f"img_{index:03d}.tif", fei_file(index))
                                              for index in range(4)])
    writer.start()
    images = collect(source, 4)
    writer.join()
    assert [image.label for image in images] == [f"img_{index:03d}.tif" for index in range(4)]
    for index, image in enumerate(images):
        np.testing.assert_array_equal(image.pixels, frame(index))  # whole, data bar cropped
        assert image.pixel_size_nm == pytest.approx(20.0) and image.dwell_ns == pytest.approx(500)
        assert image.working_distance_mm == pytest.approx(5.0) and image.detector == "ETD"
        assert image.data_bar_rows == 12
        # The scan began a frame time (rows x columns x dwell) before its file appeared.
        assert image.scan_started_at_ns < image.acquired_at_ns
    assert nothing_more(source)
    assert source.counters["files_published"] == 4 and source.counters["files_skipped"] == 0


def test_garbage_is_skipped_logged_and_counted_and_good_frames_still_come(watched, caplog):
    folder, source = watched
    caplog.set_level(logging.WARNING, logger="imageserver.watch")
    (folder / "notes.txt").write_text("not an image")
    (folder / "broken.tif").write_bytes(os.urandom(5000))
    (folder / "empty.png").write_bytes(b"")
    (folder / "zz_good.tif").write_bytes(fei_file(7))
    images = collect(source, 1)
    assert [image.label for image in images] == ["zz_good.tif"]
    deadline = time.monotonic() + 10
    while source.counters["files_skipped"] < 2 and time.monotonic() < deadline:
        with pytest.raises(NotReady):
            source.acquire()
        time.sleep(0.05)
    assert source.counters["files_skipped"] == 2 and source.counters["files_ignored"] == 1
    skipped = " ".join(record.getMessage() for record in caplog.records)
    assert "skipped broken.tif: " in skipped and "skipped empty.png: empty file" in skipped
    assert nothing_more(source, 2.5)  # the folder is listed again every second: no second try, no count
    assert source.counters["files_skipped"] == 2
    assert source.describe()["last_skipped"].startswith("skipped")


def test_deleted_and_renamed_files(watched):
    folder, source = watched
    # Deleted while still being written: never published, counted.
    with open(folder / "gone.tif", "wb") as file:
        file.write(fei_file(1)[:100])
        file.flush()
        time.sleep(0.1)
    (folder / "gone.tif").unlink()
    # Written under a temporary name, then renamed into place (an atomic save).
    (folder / "save.partial").write_bytes(fei_file(2))
    os.replace(folder / "save.partial", folder / "saved.tif")
    images = collect(source, 1)
    assert [image.label for image in images] == ["saved.tif"]
    # Renamed after it was published: the same frame, not a new one.
    os.replace(folder / "saved.tif", folder / "renamed.tif")
    assert nothing_more(source)
    assert source.counters["files_published"] == 1
    # Rewritten in place: a new frame.
    time.sleep(0.01)
    (folder / "renamed.tif").write_bytes(fei_file(3))
    again = collect(source, 1)
    assert [image.label for image in again] == ["renamed.tif"]
    np.testing.assert_array_equal(again[0].pixels, frame(3))


def test_files_already_there_are_not_frames_of_this_session_unless_asked(tmp_path):
    tifffile.imwrite(tmp_path / "old.tif", frame(0))
    source = WatchSource(tmp_path, settle_s=0.2)
    try:
        assert nothing_more(source)
        (tmp_path / "new.tif").write_bytes(fei_file(1))
        assert [image.label for image in collect(source, 1)] == ["new.tif"]
    finally:
        source.close()
    everything = WatchSource(tmp_path, settle_s=0.2, existing=True)
    try:
        assert [image.label for image in collect(everything, 2)] == ["new.tif", "old.tif"]
    finally:
        everything.close()


def test_the_users_settings_fill_what_files_do_not_say(tmp_path):
    source = WatchSource(tmp_path, settle_s=0.2, fallbacks={"dwell_ns": 100.0, "pixel_size_nm": 7.0},
                         overrides={"detector": None})
    try:
        tifffile.imwrite(tmp_path / "plain.tif", frame(0))
        (image,) = collect(source, 1)
        assert (image.pixel_size_nm, image.dwell_ns, image.magnification) == (7.0, 100.0, None)
        (tmp_path / "fei.tif").write_bytes(fei_file(1))
        (image,) = collect(source, 1)
        assert (image.pixel_size_nm, image.dwell_ns) == (pytest.approx(20.0), pytest.approx(500))  # the file's
    finally:
        source.close()


def test_a_missing_folder_is_refused_by_name(tmp_path):
    with pytest.raises(FileNotFoundError, match="no folder to watch"):
        WatchSource(tmp_path / "nope")


class Clock:
    now = 0.0

    def __call__(self) -> float:
        return self.now


def test_every_files_settle_time_runs_while_an_earlier_one_waits_and_a_batch_goes_in_name_order(tmp_path):
    """Without close events (polling), each file must be unchanged for settle_s. The
    files behind the first are timed from when they were seen, not from when the first
    was published (frames must not queue up behind one another); files found together
    go out in name order."""
    clock = Clock()
    source = WatchSource(tmp_path, settle_s=0.3, polling=True, clock=clock)
    try:
        for name in ("frame_b.tif", "frame_a.tif", "frame_c.tif"):
            tifffile.imwrite(tmp_path / name, frame(ord(name[-5])))
        deadline = time.monotonic() + 10
        while source.describe()["pending"] < 3 and time.monotonic() < deadline:
            with pytest.raises(NotReady):
                source.acquire()  # not settled yet: the clock stands still
            time.sleep(0.05)
        assert source.describe()["pending"] == 3
        clock.now = 0.31
        labels = [source.acquire().label for _ in range(3)]  # all three settled together
        assert labels == ["frame_a.tif", "frame_b.tif", "frame_c.tif"]
    finally:
        source.close()


def test_a_file_written_to_while_it_is_read_is_published_once_when_it_settles(watched, monkeypatch):
    """A CI run published a frame twice: read whole while its last chunk landed, it was
    remembered by the size before that chunk, and came back as new a second later (an
    old frame, after a move). A file that changes during the read waits, and goes out
    once, as it ends up."""
    import services.imageserver.watch as watch

    folder, source = watched
    path = folder / "frame_000.tif"
    data = fei_file(7)
    original = watch.read_sem_image
    grown = []

    def read_while_the_writer_appends(*args, **kwargs):
        image = original(*args, **kwargs)
        if not grown:  # the writer's last write lands during the first read
            with open(path, "ab") as file:
                file.write(b"\0" * 64)
            grown.append(True)
        return image

    monkeypatch.setattr(watch, "read_sem_image", read_while_the_writer_appends)
    path.write_bytes(data)
    images = collect(source, 1)
    assert grown and len(images) == 1 and images[0].label == "frame_000.tif"
    assert nothing_more(source, for_s=2.5)  # past a rescan: not published again
    assert source.describe()["files_published"] == 1


@pytest.mark.parametrize("polling", [False, True], ids=["os-events", "polling"])
def test_a_tiff_half_written_and_held_open_waits_and_keeps_its_place(tmp_path, polling):
    """A third of a TIFF written and the file held open (a writer pausing on a slow share)
    was skipped as truncated after a second, then published after the files behind it
    when its last chunk landed. It now waits (up to give_up_s), holding the later ones."""
    source = WatchSource(tmp_path, settle_s=0.3, give_up_s=10.0, polling=polling)
    try:
        data = fei_file(1)
        with open(tmp_path / "a_held.tif", "wb") as held:
            held.write(data[: len(data) // 3])
            held.flush()
            time.sleep(0.05)
            (tmp_path / "b.tif").write_bytes(fei_file(2))
            assert nothing_more(source, 2.5), "nothing while the first file is unfinished"
            held.write(data[len(data) // 3:])
        images = collect(source, 2)
        assert [image.label for image in images] == ["a_held.tif", "b.tif"]
        np.testing.assert_array_equal(images[0].pixels, frame(1))
        assert source.counters["files_skipped"] == 0
    finally:
        source.close()
