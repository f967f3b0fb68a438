"""Image files (PNG/TIFF, 8/16 bit, metadata) and the settings model."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from semservo.config import Settings, pixel_size_nm
from semservo.imagefiles import ImageFileError, list_frames, read_image, write_image


@pytest.mark.parametrize("suffix", [".png", ".tif"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_write_then_read_keeps_pixels_and_metadata(tmp_path, suffix, dtype):
    rng = np.random.default_rng(1)
    pixels = rng.integers(0, np.iinfo(dtype).max, size=(40, 56), dtype=dtype)
    path = write_image(tmp_path / f"frame{suffix}", pixels, magnification=5000, dwell_ns=360, pixel_size_nm=42.46)
    read, metadata = read_image(path)
    assert read.dtype == dtype
    np.testing.assert_array_equal(read, pixels)
    assert metadata == {"magnification": 5000.0, "dwell_ns": 360.0, "pixel_size_nm": 42.46}


def test_plain_png_has_no_metadata(tmp_path):
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(tmp_path / "plain.png")
    assert read_image(tmp_path / "plain.png")[1] == {}


def test_grey_rgb_is_accepted_and_colour_refused(tmp_path):
    grey = np.repeat(np.arange(64, dtype=np.uint8).reshape(8, 8)[..., None], 3, axis=2)
    Image.fromarray(grey).save(tmp_path / "grey.png")
    assert read_image(tmp_path / "grey.png")[0].shape == (8, 8)
    colour = grey.copy()
    colour[..., 0] = 255
    Image.fromarray(colour).save(tmp_path / "colour.png")
    with pytest.raises(ImageFileError, match="colour"):
        read_image(tmp_path / "colour.png")


def test_unreadable_file_is_named(tmp_path):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"not a png at all")
    with pytest.raises(ImageFileError, match="broken.png"):
        read_image(bad)


def test_list_frames_in_name_order_and_filtered(tmp_path):
    for name in ["b.png", "a.tif", "c.txt", "frame2.png", "frame10.png"]:
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in list_frames(tmp_path)] == ["a.tif", "b.png", "frame10.png", "frame2.png"]
    assert [p.name for p in list_frames(tmp_path, "frame*")] == ["frame10.png", "frame2.png"]
    with pytest.raises(FileNotFoundError):
        list_frames(tmp_path / "missing")


def test_pixel_size_follows_eq_43():
    assert pixel_size_nm(1200) == pytest.approx(212.3e3 / 1200)
    assert pixel_size_nm(1000, width_px=1024) == pytest.approx(106.15)  # same field, twice the pixels
    with pytest.raises(ValueError):
        pixel_size_nm(0)


def test_settings_come_from_prefixed_environment(monkeypatch):
    monkeypatch.setenv("SEMSERVO_BIND_HOST", "0.0.0.0")
    monkeypatch.setenv("SEMSERVO_IMAGESERVER__FRAMES_PORT", "6000")
    monkeypatch.setenv("SEMSERVO_IMAGESERVER__FPS", "2.5")
    settings = Settings()
    assert settings.bind(settings.imageserver.frames_port) == "tcp://0.0.0.0:6000"
    assert settings.imageserver.fps == 2.5
    assert settings.imageserver.host == "127.0.0.1"


def test_settings_refuse_bad_values(monkeypatch):
    monkeypatch.setenv("SEMSERVO_IMAGESERVER__FPS", "-1")
    with pytest.raises(ValueError, match="fps"):
        Settings()


def test_default_settings_are_loopback_and_find_the_recording(recorded_run):
    settings = Settings()
    assert settings.bind_host == "127.0.0.1"
    assert settings.imageserver.replay_dir == recorded_run


def test_a_misspelt_setting_is_named_with_the_closest_names():
    """The settings ignore names they do not know; unrecognised_settings names each
    SEMSERVO_<SECTION>__<NAME> that is not a setting of its section (what `semservo up`
    and `demo` print), and leaves alone the variables read elsewhere and the good ones."""
    from semservo.config import unrecognised_settings

    problems = unrecognised_settings({
        "SEMSERVO_FAKELAB__SAMPLE_PIXEL_NM": "50", "SEMSERVO_STAGE__BOGUS": "1",
        "SEMSERVO_ESTIMATOR__TILT_KERNEL_PX": "16", "SEMSERVO_URL": "http://x", "SEMSERVO_COMPOSE__DIR": "/tmp",
        "semservo_gateway__http_port": "8001", "PATH": "/bin"})
    assert problems == [
        "SEMSERVO_FAKELAB__SAMPLE_PIXEL_NM names no setting of fakelab, so it does nothing; did you mean "
        "SEMSERVO_FAKELAB__SAMPLE_PIXEL_SIZE_NM or SEMSERVO_FAKELAB__SAMPLE_IMAGE?",
        "SEMSERVO_STAGE__BOGUS names no setting of stage, so it does nothing"]
