"""Vendor SEM files as a lab has them: every image of ``shared/data/sem-images`` read
with its metadata and its data bar cropped, and the vendors' metadata formats that the
folder has no real file of (Thermo Fisher/FEI, Zeiss, JEOL's text file) from files
written the way those instruments write them."""

from __future__ import annotations

import io

import numpy as np
import pytest
import tifffile

from semservo.imagefiles import ImageFileError, find_data_bar, read_image, read_sem_image
from semservo.sem_metadata import FEI_TAGS, ZEISS_TAG, ImageMetadata, from_jeol_text
from services.fakelab.acquisition import encode_fei_tiff, fei_metadata_text, with_data_bar

#: What each real file is: (shape as read, dtype, data bar rows, metadata it carries).
EXPECTED = {
    "jeol_grid.tif": ((960, 1280), np.uint8, "overlay", {}),
    "tescan_aperture.tif": ((888, 1024), np.uint16, 120, {
        "pixel_size_nm": 2501.2, "magnification": 108.08, "working_distance_mm": 13.25, "dwell_ns": 3200.0,
        "high_voltage_kv": 10.0, "detector": "SE", "instrument": "TESCAN MIRA3 XMU"}),
    "fibsem_slice_cells.tif": ((1000, 1500), np.uint8, 0, {}),
    "hole_low_mag.tif": ((486, 700), np.uint8, 0, {}),
    "drift_pair_before.tif": ((520, 696), np.uint16, 0, {}),
    # Five blank (all-zero) rows at the bottom, left by the drift: not sample either.
    "drift_pair_after.tif": ((520, 696), np.uint16, 5, {}),
}


def test_the_folder_holds_the_files_this_test_knows(sem_images):
    assert {path.name for path in sem_images.glob("*.tif")} == set(EXPECTED)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_every_real_sem_image_reads_with_its_metadata_and_without_its_data_bar(sem_images, name):
    shape, dtype, bar, metadata = EXPECTED[name]
    image = read_sem_image(sem_images / name)
    assert image.file_shape == shape and image.pixels.dtype == dtype
    if bar == "overlay":  # JEOL writes its text and scale bar over the bottom of the image
        assert 40 <= image.data_bar_rows <= 80
    else:
        assert image.data_bar_rows == bar
    assert image.pixels.shape == (shape[0] - image.data_bar_rows, shape[1])
    known = image.metadata.known()
    known.pop("data_bar_rows", None)
    assert known.keys() == metadata.keys()
    for key, value in metadata.items():
        assert known[key] == (pytest.approx(value) if isinstance(value, float) else value), key
    # Nothing is made up: a file without a pixel size has none.
    if "pixel_size_nm" not in metadata:
        assert image.metadata.pixel_size_nm is None


def test_the_jeol_palette_image_is_its_grey_levels(sem_images):
    with tifffile.TiffFile(sem_images / "jeol_grid.tif") as tif:
        assert tif.pages[0].photometric == tifffile.PHOTOMETRIC.PALETTE
        assert tif.pages[0].compression == tifffile.COMPRESSION.LZW  # needs imagecodecs
        indices = tif.pages[0].asarray()
    pixels = read_sem_image(sem_images / "jeol_grid.tif", data_bar=0).pixels
    np.testing.assert_array_equal(pixels, indices)  # a grey ramp: the index is the level
    assert pixels.std() > 10


def test_the_tescan_data_bar_is_where_its_metadata_says(sem_images):
    image = read_sem_image(sem_images / "tescan_aperture.tif")
    full = read_sem_image(sem_images / "tescan_aperture.tif", data_bar=0).pixels
    bar = full[image.pixels.shape[0]:]
    # The bar's grey fill covers most of its rows; the sample above has none of it.
    fill = np.bincount(bar[-1]).argmax()
    assert (bar == fill).mean() > 0.5 and (image.pixels[-5:] == fill).mean() < 0.01
    assert find_data_bar(full) == image.data_bar_rows  # detection agrees with the metadata


def test_the_data_bar_can_be_set_by_hand(sem_images):
    assert read_sem_image(sem_images / "hole_low_mag.tif", data_bar=30).pixels.shape == (456, 700)
    assert read_sem_image(sem_images / "tescan_aperture.tif", data_bar=0).pixels.shape == (888, 1024)
    with pytest.raises(ImageFileError, match="leaves nothing"):
        read_sem_image(sem_images / "hole_low_mag.tif", data_bar=486)
    with pytest.raises(ValueError, match="data_bar"):
        read_sem_image(sem_images / "hole_low_mag.tif", data_bar=-1)


def test_images_without_a_bar_lose_no_rows(recorded_run):
    for path in sorted(recorded_run.glob("*.png")):
        image = read_sem_image(path)
        assert image.data_bar_rows == 0 and image.pixels.shape == (512, 512), path.name


def test_thermo_fisher_fei_metadata_and_data_bar():
    pixels = (np.random.default_rng(1).random((128, 160)) * 200).astype(np.uint8)
    text = fei_metadata_text(pixel_size_nm=12.5, dwell_ns=300, working_distance_mm=4.1, rows=128, cols=160,
                             high_voltage_kv=2.0, detector="TLD")
    image = read_sem_image(encode_fei_tiff(with_data_bar(pixels), text))
    np.testing.assert_array_equal(image.pixels, pixels)
    assert image.data_bar_rows == 16
    assert image.metadata == ImageMetadata(pixel_size_nm=pytest.approx(12.5), working_distance_mm=pytest.approx(4.1),
                                           dwell_ns=pytest.approx(300), high_voltage_kv=pytest.approx(2.0),
                                           detector="TLD", instrument="semservo fake lab", data_bar_rows=16)
    assert FEI_TAGS[1] == 34682


def test_zeiss_smartsem_metadata():
    text = "\r\n".join(["", "AP_IMAGE_PIXEL_SIZE", "Image Pixel Size = 2.615 nm", "AP_MAG", "Mag = 50.00 K X",
                        "AP_WD", "WD = 5.1 mm", "AP_ACTUALKV", "EHT = 3.00 kV", "DP_DETECTOR_TYPE",
                        "Detector = InLens", "DP_DWELL_TIME", "Dwell Time = 100 ns", ""])
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, np.zeros((64, 64), np.uint8), extratags=[(ZEISS_TAG, "s", 0, text, True)], metadata=None)
    metadata = read_sem_image(buffer.getvalue(), data_bar=0).metadata
    assert metadata.pixel_size_nm == pytest.approx(2.615)
    assert metadata.magnification == pytest.approx(50_000)
    assert metadata.working_distance_mm == pytest.approx(5.1)
    assert metadata.high_voltage_kv == pytest.approx(3.0)
    assert metadata.dwell_ns == pytest.approx(100)
    assert metadata.detector == "InLens"


def test_jeol_companion_text_file(tmp_path):
    pixels = np.zeros((1024, 1280), np.uint8)
    pixels[:960] = 100
    tifffile.imwrite(tmp_path / "grid.tif", pixels)
    (tmp_path / "grid.txt").write_text("$CM_FORMAT JEOL/SEM\n$CM_INSTRUMENT JSM-7100F\n$CM_SIGNAL SEI\n"
                                       "$CM_MAG 50\n$CM_ACCEL_VOLT 5.00\n$CM_FULL_SIZE 1280 960\n$CM_WD 10.2\n"
                                       "$$SM_MICRON_BAR 240\n$$SM_MICRON_MARKER 500um\n", encoding="latin-1")
    image = read_sem_image(tmp_path / "grid.tif")
    assert image.pixels.shape == (960, 1280) and image.data_bar_rows == 64
    assert image.metadata.pixel_size_nm == pytest.approx(500_000 / 240)
    assert (image.metadata.magnification, image.metadata.high_voltage_kv) == (50, 5.0)
    assert (image.metadata.detector, image.metadata.instrument) == ("SEI", "JEOL JSM-7100F")
    assert from_jeol_text("$CM_MAG nonsense\n", 960) == ImageMetadata()  # nothing made up


def test_compressions_bit_depths_and_pages(tmp_path):
    rng = np.random.default_rng(2)
    for compression in ("lzw", "zlib", "packbits", None):
        for dtype in (np.uint8, np.uint16):
            pixels = (rng.random((48, 64)) * np.iinfo(dtype).max * 0.9).astype(dtype)
            path = tmp_path / f"{compression}-{np.dtype(dtype).name}.tif"
            tifffile.imwrite(path, pixels, compression=compression)
            np.testing.assert_array_equal(read_image(path, data_bar=0)[0], pixels)
    stack = (rng.random((3, 32, 32)) * 255).astype(np.uint8)
    tifffile.imwrite(tmp_path / "stack.tif", stack, photometric="minisblack")
    np.testing.assert_array_equal(read_sem_image(tmp_path / "stack.tif", data_bar=0).pixels, stack[0])
    np.testing.assert_array_equal(read_sem_image(tmp_path / "stack.tif", data_bar=0, page=2).pixels, stack[2])
    with pytest.raises(ImageFileError, match="no page 3"):
        read_sem_image(tmp_path / "stack.tif", page=3)


def test_a_colour_palette_or_a_file_cut_short_is_refused_with_the_reason(tmp_path):
    indices = np.arange(64, dtype=np.uint8).reshape(8, 8)
    colours = np.zeros((3, 256), np.uint16)
    colours[0] = np.arange(256) * 257
    tifffile.imwrite(tmp_path / "colour.tif", indices, photometric="palette", colormap=colours)
    with pytest.raises(ImageFileError, match="colour palette"):
        read_sem_image(tmp_path / "colour.tif")
    data = (tmp_path / "colour.tif").read_bytes()
    tifffile.imwrite(tmp_path / "whole.tif", np.ones((256, 256), np.uint16))
    cut = (tmp_path / "whole.tif").read_bytes()[:-1000]
    with pytest.raises(ImageFileError, match="truncated"):
        read_sem_image(cut)
    assert data  # the colour file was written whole: the refusal is about its colours


def test_hitachi_companion_text_file(tmp_path):
    pixels = np.full((1024, 1280), 90, np.uint8)
    tifffile.imwrite(tmp_path / "cells.tif", pixels)
    (tmp_path / "cells.txt").write_text("[SemImageFile]\nInstructName=S-4800\nSignalName=SE(U)\nDataSize=1280x960\n"
                                        "PixelSize=99.21875\nMagnification=5000\nAcceleratingVoltage=5000 Volt\n"
                                        "WorkingDistance=8400 um\n", encoding="latin-1")
    image = read_sem_image(tmp_path / "cells.tif")
    assert image.pixels.shape == (960, 1280) and image.data_bar_rows == 64
    metadata = image.metadata
    assert metadata.pixel_size_nm == pytest.approx(99.21875) and metadata.magnification == 5000
    assert metadata.high_voltage_kv == pytest.approx(5.0) and metadata.working_distance_mm == pytest.approx(8.4)
    assert (metadata.detector, metadata.instrument) == ("SE(U)", "Hitachi S-4800")


def test_an_imagej_calibrated_tiff_gives_its_pixel_size(tmp_path):
    tifffile.imwrite(tmp_path / "fiji.tif", np.zeros((32, 48), np.uint8), imagej=True,
                     resolution=(1 / 0.025, 1 / 0.025), metadata={"unit": "micron"})
    assert read_sem_image(tmp_path / "fiji.tif").metadata.pixel_size_nm == pytest.approx(25.0)
    tifffile.imwrite(tmp_path / "pixels.tif", np.zeros((32, 48), np.uint8), imagej=True, metadata={"unit": "pixel"})
    assert read_sem_image(tmp_path / "pixels.tif").metadata.pixel_size_nm is None  # uncalibrated: unknown


def test_a_stream_keeps_the_crop_its_first_frame_of_a_size_had(sem_images, tmp_path):
    """Replayed (or watched) together, the drift pair's second frame lost its 5 blank rows
    to detection: the replay refused to start ('(515, 696) differs from (520, 696)') and a
    watched folder refused every frame after a teach. A stream decides once per size."""
    from services.imageserver.sources import ReplaySource

    for name in ("drift_pair_before.tif", "drift_pair_after.tif"):
        (tmp_path / name).symlink_to(sem_images / name)
    replay = ReplaySource(tmp_path)
    shapes = {pixels.shape for pixels, _ in replay.images}
    assert shapes == {(515, 696)}, "the first file in order (after) decides: 5 rows for both"
    detected: dict = {}
    first = read_sem_image(sem_images / "drift_pair_before.tif", detected=detected)
    second = read_sem_image(sem_images / "drift_pair_after.tif", detected=detected)
    assert first.pixels.shape == second.pixels.shape == (520, 696)
    assert read_sem_image(sem_images / "drift_pair_after.tif").pixels.shape == (515, 696), "alone, as before"
