"""A real SEM image as the simulated lab's sample (semservo.simulation.sample_image): its
scale, its edges, its height map, its noise, and the refusals."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import tifffile
from PIL import Image

from semservo.estimation import MotionEstimator
from semservo.messages import ScanRequest
from semservo.simulation.sample_image import SampleImage, SampleImageError, magnification_for, noise_sigma
from semservo.simulation.sem import Pose, ScanSettings, image_point, sample_point, view_error_px
from semservo.simulation.world import PRESETS, World
from services.fakelab.scan import scan_settings


def render(world: World, settings: ScanSettings, pose: Pose = Pose(), seed: int = 0) -> np.ndarray:
    return world.sem.render(settings, [pose] * settings.rows, [pose] * settings.rows, np.random.default_rng(seed))


def scan_of(world: World, magnification: float | None = None, **changes) -> ScanSettings:
    preset = world.preset
    return ScanSettings(dwell_ns=preset.dwell_ns, magnification=magnification or preset.magnification,
                        working_distance_um=preset.focus_um, **changes)


def correlation(first: np.ndarray, second: np.ndarray) -> float:
    first, second = (np.asarray(a, np.float64) for a in (first, second))
    first, second = first - first.mean(), second - second.mean()
    return float((first * second).sum() / np.sqrt((first ** 2).sum() * (second ** 2).sum()))


@pytest.fixture(scope="module")
def jeol(sem_images) -> SampleImage:
    """A real picture, at the optimal preset's pixel (x1200, 177 nm)."""
    return SampleImage.open(sem_images / "jeol_grid.tif", pixel_size_nm=176.9)


def test_a_frame_shows_the_pictures_centre_at_its_own_scale(jeol):
    world = World(PRESETS["optimal"], sample_image=jeol)
    assert world.preset.magnification == pytest.approx(magnification_for(jeol.pixel_um, 512))
    frame = render(world, scan_of(world))
    rows, cols = jeol.shape
    centre = jeol.intensity[rows // 2 - 256: rows // 2 + 256, cols // 2 - 256: cols // 2 + 256]
    assert correlation(frame, centre) > 0.9
    # Off by a few pixels, or at another scale, it is not the same picture.
    assert correlation(frame, jeol.intensity[rows // 2 - 256: rows // 2 + 256, cols // 2 - 250: cols // 2 + 262]) < 0.8


def test_a_coarser_scan_shows_the_picture_averaged_down(jeol):
    import cv2

    world = World(PRESETS["optimal"], sample_image=jeol)
    frame = render(world, scan_of(world, magnification=world.preset.magnification / 1.5))
    rows, cols = jeol.shape
    half = int(round(256 * 1.5))
    crop = jeol.intensity[rows // 2 - half: rows // 2 + half, cols // 2 - half: cols // 2 + half]
    assert correlation(frame, cv2.resize(crop, (512, 512), interpolation=cv2.INTER_AREA)) > 0.9


@pytest.mark.parametrize("ratio", [1.0, 0.6, 1.8])
def test_the_texture_has_the_expected_period_in_the_frame(ratio):
    """Stripes 16 picture pixels apart are 16 x P_picture / P_scan frame pixels apart."""
    columns = np.arange(1200)
    stripes = (120 + 80 * np.sin(2 * np.pi * columns / 16.0)).astype(np.uint8)
    picture = np.tile(stripes, (1000, 1))
    sample = SampleImage.from_array(picture, 0.1, denoise_strength=0)
    world = World(PRESETS["optimal"], sample_image=sample)
    magnification = world.preset.magnification * ratio
    frame = render(world, scan_of(world, magnification=magnification)).astype(np.float64)
    spectrum = np.abs(np.fft.rfft(frame.mean(axis=0) - frame.mean()))
    peak = int(np.argmax(spectrum[2:])) + 2
    expected_period = 16.0 * ratio  # the scan pixel is the picture pixel / ratio
    assert 512 / peak == pytest.approx(expected_period, rel=0.06)


def test_a_jog_moves_the_picture_by_the_expected_pixels(jeol):
    world = World(PRESETS["optimal"], sample_image=jeol)
    settings = scan_of(world)
    estimator = MotionEstimator(render(world, settings, seed=1), rotation=False)
    for x_um, y_um in ((2.0, -1.0), (-7.3, 4.1)):
        motion = estimator.estimate(render(world, settings, Pose(x_um=x_um, y_um=y_um), seed=2))
        assert motion.dx == pytest.approx(x_um / settings.pixel_um, abs=0.1)
        assert motion.dy == pytest.approx(y_um / settings.pixel_um, abs=0.1)


def test_the_view_error_follows_the_rendering_under_tilt(jeol):
    """view_error_px is the geometry the frames are rendered with: a tilted, shifted
    pose moves the content at the centre by what it predicts (the pivot's lever too)."""
    world = World(PRESETS["optimal"], sample_image=jeol)
    settings = scan_of(world)
    estimator = MotionEstimator(render(world, settings, seed=1), rotation=False)
    pose = Pose(x_um=1.0, y_um=-0.5, tilt_x_deg=0.8, tilt_y_deg=-0.6)
    motion = estimator.estimate(render(world, settings, pose, seed=2))
    predicted = view_error_px(pose, Pose(), settings.pixel_um)
    assert abs(predicted[0] - 1.0 / settings.pixel_um) > 0.5  # the lever shows
    assert motion.dx == pytest.approx(predicted[0], abs=0.15)
    assert motion.dy == pytest.approx(predicted[1], abs=0.15)
    point = sample_point(pose, 3.0, -2.0)
    assert image_point(pose, *point) == pytest.approx((3.0, -2.0))


def small_picture() -> np.ndarray:
    rng = np.random.default_rng(3)
    return (rng.random((100, 100)) * 200 + 20).astype(np.uint8)


@pytest.mark.parametrize("edges", ["mirror", "tile", "pad"])
def test_beyond_the_pictures_edges(edges):
    picture = small_picture()
    sample = SampleImage.from_array(picture, 1.0, edges=edges, denoise_strength=0)
    # The grid at the picture's pixel, two pictures wide: grid column 50 + j is picture column j.
    raster = sample.rasterize(1.0, 200.0).intensity
    inside = raster[50:150, 50:150]
    assert np.allclose(inside, sample.intensity, atol=1e-4)
    right = raster[50:150, 150:160]
    if edges == "mirror":  # reflected about the last column, no seam
        assert np.allclose(right, sample.intensity[:, -2:-12:-1], atol=1e-4)
    elif edges == "tile":  # the left edge again
        assert np.allclose(right, sample.intensity[:, :10], atol=1e-4)
    else:  # flat, the picture's median yield
        assert np.allclose(right, np.median(sample.intensity), atol=1e-4)


def test_a_height_map_makes_a_defocus_difference():
    """A part of a flat picture raised by 10 um: in the tilts preset's small depth of
    field, focused on the median height (the low part), the raised part is blurred;
    without the height map both parts are equally sharp."""
    rng = np.random.default_rng(5)
    picture = (rng.random((1024, 1024)) * 200 + 20).astype(np.uint8)
    heights = np.zeros((1024, 1024), np.uint8)
    heights[:, 640:] = 255  # frame columns 384 on (the frame is the picture's middle 512)
    flat = SampleImage.from_array(picture, 0.0708, denoise_strength=0)
    raised = SampleImage.from_array(picture, 0.0708, height_map=heights, height_um=10.0, denoise_strength=0)
    assert raised.height_range_um == 10.0 and raised.median_height_um == 0.0

    def sharpness(world: World) -> tuple[float, float]:
        frame = render(world, scan_of(world), seed=4).astype(np.float64)
        detail = np.abs(np.diff(frame, axis=1))
        return float(detail[:, 40:340].mean()), float(detail[:, 400:500].mean())

    low, high = sharpness(World(PRESETS["tilts"], sample_image=flat))
    assert low == pytest.approx(high, rel=0.1)
    low, high = sharpness(World(PRESETS["tilts"], sample_image=raised))
    assert low > 1.5 * high


def test_its_own_noise_is_estimated_and_removed():
    rng = np.random.default_rng(6)
    smooth = np.add.outer(np.linspace(0, 1, 600), np.linspace(0, 1, 800)) / 2
    picture = np.clip(60 + 130 * smooth + rng.normal(0, 8, smooth.shape), 0, 255).astype(np.uint8)
    kept = SampleImage.from_array(picture, 0.1, denoise_strength=0)
    cleaned = SampleImage.from_array(picture, 0.1)
    # 8 grey levels, in yield: the percentiles' span of grey is 0.8 of yield.
    low, high = np.percentile(picture, [0.5, 99.5])
    assert kept.noise_before == pytest.approx(8 * 0.8 / (high - low), rel=0.2)
    assert kept.noise_after == pytest.approx(kept.noise_before)
    assert cleaned.noise_after < 0.3 * cleaned.noise_before
    assert noise_sigma(np.zeros((50, 50))) == 0.0


def test_8_and_16_bit_pictures_are_the_same_sample():
    picture = small_picture()
    eight = SampleImage.from_array(picture, 0.1, denoise_strength=0)
    sixteen = SampleImage.from_array(picture.astype(np.uint16) * 257 // 4, 0.1, denoise_strength=0)
    assert np.allclose(eight.intensity, sixteen.intensity, atol=1e-4)


def test_the_pixel_size_comes_from_the_file_or_the_option(tmp_path, sem_images):
    tescan = SampleImage.open(sem_images / "tescan_aperture.tif")
    assert tescan.pixel_size_from == "metadata" and tescan.pixel_um == pytest.approx(2.5012)
    assert tescan.data_bar_rows == 120  # cropped: the data bar is not sample
    given = SampleImage.open(sem_images / "tescan_aperture.tif", pixel_size_nm=100)
    assert given.pixel_size_from == "setting" and given.pixel_um == pytest.approx(0.1)
    path = tmp_path / "plain.png"
    Image.fromarray(small_picture()).save(path)
    with pytest.raises(SampleImageError, match="does not say its pixel size.*--sample-pixel-nm"):
        SampleImage.open(path)
    assert SampleImage.open(path, pixel_size_nm=50).pixel_um == pytest.approx(0.05)


def test_refusals_say_why(tmp_path):
    garbage = tmp_path / "garbage.tif"
    garbage.write_bytes(b"II*\x00 this is not a TIFF")
    with pytest.raises(SampleImageError, match="cannot read the sample image.*garbage.tif"):
        SampleImage.open(garbage, pixel_size_nm=100)
    with pytest.raises(SampleImageError, match="no such sample image file"):
        SampleImage.open(tmp_path / "missing.tif", pixel_size_nm=100)
    with pytest.raises(SampleImageError, match="array: the image is .*one grey level"):
        SampleImage.from_array(np.full((100, 100), 7, np.uint8), 0.1)
    with pytest.raises(SampleImageError, match="too small"):
        SampleImage.from_array(np.zeros((30, 100), np.uint8), 0.1)
    picture = tmp_path / "picture.tif"
    tifffile.imwrite(picture, small_picture())
    heights = tmp_path / "heights.tif"
    tifffile.imwrite(heights, np.zeros((100, 300), np.uint8))
    with pytest.raises(SampleImageError, match="needs the height of its brightest level"):
        SampleImage.open(picture, pixel_size_nm=100, height_image=heights)
    with pytest.raises(SampleImageError, match="same aspect ratio"):
        SampleImage.open(picture, pixel_size_nm=100, height_image=heights, height_um=2.0)
    with pytest.raises(SampleImageError, match="a folder, not a sample image file"):
        SampleImage.open(tmp_path, pixel_size_nm=100)
    holes = np.zeros(small_picture().shape, np.float32)
    holes[10:20, 10:20] = np.nan
    tifffile.imwrite(heights, holes)
    with pytest.raises(SampleImageError, match="height map has 100 NaN or infinite pixels"):
        SampleImage.open(picture, pixel_size_nm=100, height_image=heights, height_um=2.0)
    for pixel_um in (1e-9, 2e3, float("nan")):  # finer than 0.01 nm (frames would stall), over 1 mm, NaN
        with pytest.raises(SampleImageError, match="pixel size must be 0.01-1e.06 nm"):
            SampleImage.from_array(small_picture(), pixel_um)


@pytest.mark.parametrize("option, value, says", [
    ("--sample-pixel-nm", "nan", "must be a number from 0.01 up to 1e+06"),
    ("--sample-pixel-nm", "1e-6", "must be a number from 0.01 up to 1e+06"),
    ("--sample-pixel-nm", "abc", "not a number"),
    ("--sample-height-um", "0", "must be a number above 0 up to 10000"),
    ("--sample-denoise", "inf", "must be a number from 0 up to 10"),
    ("--sample-max-upsampling", "0.5", "must be a number from 1 up to 100"),
    ("--sample-max-field", "-1", "must be a number above 0 up to 100"),
    ("--sample-data-bar", "-3", "must be auto or a number of rows"),
])
def test_an_option_out_of_its_range_is_refused_naming_the_option(capsys, option, value, says):
    """Each --sample-* option is checked as it is read (NaN and infinities included), so
    the error names the option, not the setting it becomes."""
    import argparse

    from semservo.simulation import sample_image

    parser = argparse.ArgumentParser(prog="semservo up")
    sample_image.add_arguments(parser)
    with pytest.raises(SystemExit) as stopped:
        parser.parse_args(["--sample-image", "x.tif", option, value])
    assert stopped.value.code == 2
    assert f"argument {option}: {says}" in capsys.readouterr().err


def test_scans_beyond_the_picture_are_refused_with_the_magnifications_allowed(jeol):
    world = World(PRESETS["optimal"], sample_image=jeol)
    low, high = jeol.magnification_range()
    assert low < world.preset.magnification < high
    with pytest.raises(ValueError, match=r"larger than 1 times the sample image .*scan at x\d+"):
        scan_settings(world, ScanRequest(magnification=low * 0.9))
    with pytest.raises(ValueError, match=r"finer than the sample image.*no such detail.*scan at x\d+ or less"):
        scan_settings(world, ScanRequest(magnification=high * 1.1))
    assert scan_settings(world, ScanRequest(magnification=low * 1.01)).magnification == pytest.approx(low * 1.01)
    # A picture too small for a 512 x 512 frame even interpolated twice is refused at start.
    with pytest.raises(SampleImageError, match="too small for a 512 x 512 scan"):
        World(PRESETS["optimal"], sample_image=SampleImage.from_array(small_picture(), 0.1))


def test_the_sample_stays_when_the_preset_changes(jeol):
    world = World(PRESETS["optimal"], sample_image=jeol)
    world.set_preset(PRESETS["tilts"])
    assert world.preset.name == "tilts" and world.preset.scene == "image:jeol_grid.tif"
    assert world.preset.aperture_um == PRESETS["tilts"].aperture_um
    assert world.sem.sample_image is jeol
    assert world.describe()["sample_image"]["name"] == "jeol_grid.tif"


def test_the_command_line_refuses_a_picture_without_a_pixel_size_before_starting(tmp_path):
    path = tmp_path / "plain.png"
    Image.fromarray(small_picture()).save(path)
    done = subprocess.run([sys.executable, "-m", "semservo", "up", "--sample-image", str(path)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "sample image refused" in done.stderr and "--sample-pixel-nm" in done.stderr
    done = subprocess.run([sys.executable, "-m", "semservo", "fakelab", "--sample-image", str(tmp_path / "nope.tif")],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode != 0 and "no such sample image file" in done.stderr


def test_the_options_become_settings_and_the_depth_of_field_follows_the_scale(monkeypatch, tmp_path, sem_images):
    """`--sample-*` options are SEMSERVO_FAKELAB__SAMPLE_* settings (paths made absolute);
    the estimator's depth of field for the tilt sweeps follows the picture's scale, 2 P /
    alpha: the tilts preset's 3.5 um at its own pixel, 35 um at ten times it."""
    import argparse

    from semservo.config import Settings
    from semservo.simulation import sample_image

    parser = argparse.ArgumentParser()
    sample_image.add_arguments(parser)
    monkeypatch.chdir(sem_images)
    args = parser.parse_args(["--sample-image", "jeol_grid.tif", "--sample-pixel-nm", "70.77",
                              "--sample-edges", "tile"])
    variables = sample_image.environment_from_arguments(args)
    assert variables == {"SEMSERVO_FAKELAB__SAMPLE_IMAGE": str(sem_images.resolve() / "jeol_grid.tif"),
                         "SEMSERVO_FAKELAB__SAMPLE_PIXEL_SIZE_NM": "70.77", "SEMSERVO_FAKELAB__SAMPLE_EDGES": "tile"}
    for name, value in {**variables, "SEMSERVO_FAKELAB__PRESET": "tilts"}.items():
        monkeypatch.setenv(name, value)
    settings = Settings()
    assert settings.fakelab.sample_edges == "tile"
    derived = sample_image.system_environment(settings)
    assert float(derived["SEMSERVO_ESTIMATOR__TILT_DEPTH_OF_FIELD_UM"]) == pytest.approx(3.54, abs=0.01)
    assert float(derived["SEMSERVO_ESTIMATOR__TILT_CENTRE_UM"]) == 0.0
    monkeypatch.setenv("SEMSERVO_FAKELAB__SAMPLE_PIXEL_SIZE_NM", "707.7")
    derived = sample_image.system_environment(Settings())
    assert float(derived["SEMSERVO_ESTIMATOR__TILT_DEPTH_OF_FIELD_UM"]) == pytest.approx(35.4, abs=0.1)
    # A scale whose depth of field the tilts' sweeps cannot take is refused, saying the largest pixel.
    monkeypatch.setenv("SEMSERVO_FAKELAB__SAMPLE_PIXEL_SIZE_NM", "1e6")
    with pytest.raises(sample_image.SampleImageError, match=r"over the 10000 um .* at most 2e\+05 nm"):
        sample_image.system_environment(Settings())
    monkeypatch.delenv("SEMSERVO_FAKELAB__SAMPLE_IMAGE")
    assert sample_image.system_environment(Settings()) == {}


def test_sample_options_that_would_not_be_seen_are_named(monkeypatch, capsys, sem_images):
    """`up` and `demo` say which --sample-* options have no effect: without a picture, a
    height without a height map, a picture while the frames come from a recording."""
    from semservo import cli
    from semservo.config import Settings

    monkeypatch.setenv("SEMSERVO_FAKELAB__SAMPLE_PIXEL_SIZE_NM", "50")
    monkeypatch.setenv("SEMSERVO_FAKELAB__SAMPLE_EDGES", "tile")
    cli._warn_unused_sample_options("up", Settings())
    assert "--sample-pixel-nm, --sample-edges have no effect without --sample-image" in capsys.readouterr().err
    monkeypatch.setenv("SEMSERVO_FAKELAB__SAMPLE_IMAGE", str(sem_images / "jeol_grid.tif"))
    monkeypatch.setenv("SEMSERVO_FAKELAB__SAMPLE_HEIGHT_UM", "2")
    cli._warn_unused_sample_options("up", Settings())
    assert "--sample-height-um has no effect without --sample-height-image" in capsys.readouterr().err
    monkeypatch.delenv("SEMSERVO_FAKELAB__SAMPLE_HEIGHT_UM")
    monkeypatch.setenv("SEMSERVO_IMAGESERVER__SOURCE", "replay")
    cli._warn_unused_sample_options("up", Settings())
    assert "frames come from the replay source: they will not show it" in capsys.readouterr().err
    monkeypatch.setenv("SEMSERVO_IMAGESERVER__SOURCE", "sim")
    cli._warn_unused_sample_options("up", Settings())
    assert capsys.readouterr().err == ""
