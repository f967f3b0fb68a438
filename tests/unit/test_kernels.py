"""The estimator's fused numba kernels against plain numpy references."""

from __future__ import annotations

import numpy as np
import pytest

from semservo.estimation import _kernels
from semservo.estimation.snr import frame_statistics
from semservo.estimation.translation import foroosh_subpixel, normalized_cross_power

rng = np.random.default_rng(0)


@pytest.mark.parametrize("shift", [(0, 0), (3, -5), (-2, 7), (0, 79), (0, -80), (64, 0)])
def test_apodize_into_and_apodize_halve_into_match_numpy(shift):
    rows_shift, cols_shift = shift
    image = rng.random((64, 80)).astype(np.float32)
    window = rng.random((64, 80)).astype(np.float32)
    moved = np.zeros_like(window)
    ys, xs = np.mgrid[0:64, 0:80]
    wy, wx = ys - rows_shift, xs - cols_shift
    inside = (wy >= 0) & (wy < 64) & (wx >= 0) & (wx < 80)
    moved[inside] = window[wy[inside], wx[inside]]
    expected = (image - 0.3) * moved
    full = np.empty_like(image)
    _kernels.apodize_into(image, 0.3, window, rows_shift, cols_shift, full)
    np.testing.assert_allclose(full, expected, atol=1e-6)
    halved = np.empty((32, 40), np.float32)
    _kernels.apodize_halve_into(image, 0.3, window, rows_shift, cols_shift, np.empty((64, 40), np.float32), halved)
    np.testing.assert_allclose(halved, expected.reshape(32, 2, 40, 2).mean(axis=(1, 3)), atol=1e-6)


def test_peak_sidelobe_and_foroosh_match_numpy():
    for _ in range(20):
        surface = rng.random((32, 48)).astype(np.float32)
        row, col = int(rng.integers(0, 32)), int(rng.integers(0, 48))
        surface[row, col] = 5.0
        peak_row, peak_col, height, psr = _kernels.peak_and_sidelobe(surface, 5)
        assert (peak_row, peak_col, height) == (row, col, 5.0)
        box = np.zeros_like(surface, bool)
        box[np.ix_(np.arange(row - 5, row + 6) % 32, np.arange(col - 5, col + 6) % 48)] = True
        sidelobe = surface[~box].astype(np.float64)
        assert psr == pytest.approx((5.0 - sidelobe.mean()) / sidelobe.std(), rel=1e-4)
        assert _kernels.foroosh_offsets(surface, row, col) == pytest.approx(foroosh_subpixel(surface, (row, col)))


def test_frame_statistics_match_numpy_and_catch_non_finite_values():
    image = rng.random((300, 200)).astype(np.float32)
    mean, finite, r0, down1, down2, along1, along2 = frame_statistics(image)
    centred = image[75:225].astype(np.float64) - image.mean()
    assert finite and mean == pytest.approx(image.mean(), rel=1e-6)
    assert r0 == pytest.approx(np.mean(centred**2), rel=1e-5)
    assert down1 == pytest.approx(np.mean(centred[1:] * centred[:-1]), rel=1e-4, abs=1e-6)
    assert along2 == pytest.approx(np.mean(centred[:, 2:] * centred[:, :-2]), rel=1e-4, abs=1e-6)
    image[5, 7] = np.nan
    assert not frame_statistics(image)[1]


def test_normalized_cross_power_kernel_matches_eq_18():
    current = (rng.normal(size=(16, 9)) + 1j * rng.normal(size=(16, 9))).astype(np.complex64)
    reference = (rng.normal(size=(16, 9)) + 1j * rng.normal(size=(16, 9))).astype(np.complex64)
    weight = rng.random((16, 9)).astype(np.float32)
    out = np.empty_like(current)
    _kernels.normalized_cross_power_into(current, np.conj(reference), weight, True, out)
    expected, _ = normalized_cross_power(current, np.conj(reference))
    np.testing.assert_allclose(out, expected * weight, rtol=1e-5, atol=1e-6)


def test_normalized_angular_cross_matches_the_numpy_einsum():
    def complex_random(*shape):
        return (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(np.complex64)

    current, references, ramps = complex_random(96, 361), complex_random(4, 96, 361), complex_random(4, 361)
    crosses = np.einsum("ij,kij->kj", current, references)
    expected = np.einsum("kj,kj->j", crosses / np.abs(crosses), ramps)
    out = np.empty(361, np.complex64)
    _kernels.normalized_angular_cross_into(current, references, ramps, np.empty(361, np.complex64), out)
    np.testing.assert_allclose(out, expected, rtol=1e-4, atol=1e-4)
    # A zero cross spectrum stays zero instead of dividing by zero.
    _kernels.normalized_angular_cross_into(np.zeros_like(current), references[:1], ramps[:1],
                                           np.empty(361, np.complex64), out)
    assert np.all(out == 0)


def test_the_kernels_live_in_the_estimation_package_and_their_compiled_code_is_cached(tmp_path):
    """A fresh process compiles the kernels once; the next one loads them from numba's
    on-disk cache (here under ``NUMBA_CACHE_DIR``), with no recompilation."""
    import os
    import subprocess
    import sys

    assert _kernels.__name__ == "semservo.estimation._kernels"
    script = (
        "import numpy as np\n"
        "from semservo.estimation import MotionEstimator, _kernels\n"
        "image = np.random.default_rng(1).random((128, 128))\n"
        "MotionEstimator(image, fft_effort='FFTW_ESTIMATE').estimate(np.roll(image, 3, axis=1))\n"
        "kernels = [getattr(_kernels, name) for name in dir(_kernels) if hasattr(getattr(_kernels, name), 'stats')]\n"
        "print(sum(len(k.stats.cache_hits) for k in kernels), sum(len(k.stats.cache_misses) for k in kernels))\n"
    )
    environment = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}

    def hits_and_misses() -> tuple[int, int]:
        done = subprocess.run([sys.executable, "-c", script], env=environment, capture_output=True, text=True,
                              timeout=300, check=True)
        hits, misses = done.stdout.split()
        return int(hits), int(misses)

    hits, misses = hits_and_misses()
    assert misses > 0 and hits == 0  # an empty cache: compiled
    hits, misses = hits_and_misses()
    assert hits > 0 and misses == 0  # loaded from disk
