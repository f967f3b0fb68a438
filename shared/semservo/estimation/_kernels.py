"""Fused per-pixel loops of the estimator's per-frame path, compiled with numba.

Each is one pass over the data where numpy would make several (and allocate between
them); the FFTs themselves stay with FFTW. They are private helpers of
:mod:`semservo.estimation` (this package), whose modules document what they compute
and cite the paper. Compiled code is cached on disk (``cache=True``: numba keeps it in
this package's ``__pycache__``; under ``NUMBA_CACHE_DIR`` when that is set, or numba's
user-wide cache when the package is not writable), so only the first run pays the JIT.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# Reassociation lets reductions vectorize; the flags that assume no NaN or infinity
# ('nnan', 'ninf') are left out because frame_statistics must see them.
_jit = numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract", "nsz", "arcp"})


@_jit
def frame_statistics(image: np.ndarray, first_row: int, last_row: int):
    """(mean, all finite, R0, row lag 1, row lag 2, column lag 1, column lag 2).

    The mean and the finiteness check cover the whole image; the autocorrelation sums
    (of the mean-free image) cover rows [first_row, last_row).
    """
    rows, cols = image.shape
    total = 0.0
    for y in range(rows):
        row_total = 0.0
        for x in range(cols):
            row_total += image[y, x]
        total += row_total
    mean = total / (rows * cols)
    if not math.isfinite(mean):
        return mean, False, 0.0, 0.0, 0.0, 0.0, 0.0
    r0 = down1 = down2 = along1 = along2 = 0.0
    for y in range(first_row, last_row):
        for x in range(cols - 2):
            c = image[y, x] - mean
            r0 += c * c
            along1 += c * (image[y, x + 1] - mean)
            along2 += c * (image[y, x + 2] - mean)
        for x in range(cols - 2, cols):
            c = image[y, x] - mean
            r0 += c * c
        c = image[y, cols - 2] - mean
        along1 += c * (image[y, cols - 1] - mean)
    for y in range(first_row, last_row - 1):
        for x in range(cols):
            down1 += (image[y, x] - mean) * (image[y + 1, x] - mean)
    for y in range(first_row, last_row - 2):
        for x in range(cols):
            down2 += (image[y, x] - mean) * (image[y + 2, x] - mean)
    count = last_row - first_row
    return (
        mean,
        True,
        r0 / (count * cols),
        down1 / ((count - 1) * cols),
        down2 / ((count - 2) * cols),
        along1 / (count * (cols - 1)),
        along2 / (count * (cols - 2)),
    )


@_jit
def apodize_into(image: np.ndarray, mean: float, window: np.ndarray, row_shift: int, col_shift: int,
                 out: np.ndarray) -> None:
    """out[y, x] = (image[y, x] - mean) * window[y - row_shift, x - col_shift], zero where
    the moved window does not reach."""
    rows, cols = image.shape
    first_row, last_row = max(0, row_shift), min(rows, rows + row_shift)
    first_col, last_col = max(0, col_shift), min(cols, cols + col_shift)
    for y in range(rows):
        target = out[y]
        if y < first_row or y >= last_row or first_col >= last_col:
            for x in range(cols):
                target[x] = 0.0
            continue
        for x in range(first_col):
            target[x] = 0.0
        for x in range(last_col, cols):
            target[x] = 0.0
        # Row views indexed from 0: no wrap-around checks, so the loop vectorizes.
        pixels = image[y, first_col:last_col]
        weights = window[y - row_shift, first_col - col_shift:last_col - col_shift]
        inside = target[first_col:last_col]
        for k in range(pixels.shape[0]):
            inside[k] = (pixels[k] - mean) * weights[k]


@_jit
def normalized_cross_power_into(current: np.ndarray, reference_conjugate: np.ndarray, weight: np.ndarray,
                                use_weight: bool, out: np.ndarray) -> None:
    """out = weight * (G conj(F)) / |G conj(F)| (eq. 18), in one pass."""
    rows, cols = current.shape
    for y in range(rows):
        for x in range(cols):
            cross = current[y, x] * reference_conjugate[y, x]
            power = cross.real * cross.real + cross.imag * cross.imag
            scale = 1.0 / math.sqrt(power) if power > 0.0 else 0.0
            if use_weight:
                scale *= weight[y, x]
            out[y, x] = cross * scale


@_jit
def newton_on_band(current: np.ndarray, reference_conjugate: np.ndarray, band_rows: np.ndarray,
                   frequency_rows: np.ndarray, frequency_cols: np.ndarray, weights: np.ndarray,
                   dy: float, dx: float, iterations: int, tolerance: float, weighted: np.ndarray,
                   correlation: bool):
    """Maximize f(d) = Re sum_k w(k) |C(k)| Psi(k) e^{i 2 pi k.d} over the band by Newton.

    C = G conj(F) is the cross-power spectrum, so f is the magnitude-weighted,
    band-limited phase-correlation surface evaluated at the continuous shift d: its
    maximum is the sub-pixel shift. Gradient and Hessian are sums over the band; the
    band is given as a list of spectrum rows (``band_rows``) times the first
    ``frequency_cols.size`` columns. ``weighted`` is a (rows, cols) complex workspace.

    Returns (dy, dx, steps, correlation): with ``correlation`` set, f at the final d over
    sqrt(sum w |G|^2 * sum w |F|^2), a normalized cross-correlation in [-1, 1] of the
    band-limited images (1 when the current is the reference moved by d); else 0.
    """
    two_pi = 2.0 * math.pi
    band_height = band_rows.size
    band_width = frequency_cols.size
    # Gather the weighted cross-power over the band once.
    current_energy = 0.0
    reference_energy = 0.0
    for i in range(band_height):
        row = band_rows[i]
        for j in range(band_width):
            c = current[row, j]
            r = reference_conjugate[row, j]
            w = weights[i, j]
            weighted[i, j] = w * (c * r)
            if correlation:
                current_energy += w * (c.real * c.real + c.imag * c.imag)
                reference_energy += w * (r.real * r.real + r.imag * r.imag)
    steps = 0
    row_ramp = np.empty(band_height, dtype=np.complex128)
    col_ramp = np.empty(band_width, dtype=np.complex128)
    for _ in range(iterations):
        steps += 1
        # e^{i 2 pi (u dx + v dy)} = row_ramp[i] * col_ramp[j]: per row, three sums
        # over the columns (weighted by 1, u, u^2) carry every term of the gradient and
        # Hessian, with complex multiplies only.
        for i in range(band_height):
            phase = two_pi * frequency_rows[i] * dy
            row_ramp[i] = complex(math.cos(phase), math.sin(phase))
        for j in range(band_width):
            phase = two_pi * frequency_cols[j] * dx
            col_ramp[j] = complex(math.cos(phase), math.sin(phase))
        gu = gv = huu = hvv = huv = 0.0
        for i in range(band_height):
            s0 = 0j
            s1 = 0j
            s2 = 0j
            for j in range(band_width):
                z = weighted[i, j] * col_ramp[j]
                u = frequency_cols[j]
                s0 += z
                s1 += u * z
                s2 += (u * u) * z
            t = row_ramp[i]
            v = frequency_rows[i]
            z0 = t * s0
            z1 = t * s1
            z2 = t * s2
            gu += z1.imag
            gv += v * z0.imag
            huu += z2.real
            hvv += v * v * z0.real
            huv += v * z1.real
        determinant = huu * hvv - huv * huv
        if determinant <= 0.0 or huu <= 0.0:
            break  # not near a maximum: keep the estimate
        # Newton step d <- d - H^-1 grad f, with grad f = -2 pi g and H = -4 pi^2 M.
        step_x = -(hvv * gu - huv * gv) / determinant / two_pi
        step_y = -(huu * gv - huv * gu) / determinant / two_pi
        dx += step_x
        dy += step_y
        if abs(step_x) < tolerance and abs(step_y) < tolerance:
            break
    if not correlation:
        return dy, dx, steps, 0.0
    # f at the final d (one more pass of the zero-order sum).
    for j in range(band_width):
        phase = two_pi * frequency_cols[j] * dx
        col_ramp[j] = complex(math.cos(phase), math.sin(phase))
    value = 0.0
    for i in range(band_height):
        phase = two_pi * frequency_rows[i] * dy
        s0 = 0j
        for j in range(band_width):
            s0 += weighted[i, j] * col_ramp[j]
        value += (complex(math.cos(phase), math.sin(phase)) * s0).real
    scale = math.sqrt(current_energy * reference_energy)
    return dy, dx, steps, value / scale if scale > 0.0 else 0.0


@_jit
def decimate_apodize_into(image: np.ndarray, mean: float, window: np.ndarray, scratch: np.ndarray,
                          block_out: np.ndarray, out: np.ndarray) -> None:
    """Halve ``image`` with the binomial [1, 5, 10, 10, 5, 1] / 32 filter (separable,
    borders clamped) into ``block_out``; out = (block_out - mean) * window.

    The filter is centred where a 2 x 2 block's centre is, so the geometry is that of
    block averaging, but its response cos^5(pi f) (a block mean's is cos(pi f)) all but
    removes what would alias onto the half-resolution grid: aliased components carry
    wrong phases, which a sub-pixel fit reads as motion. What it also damps lies above
    the band the fit uses. ``scratch`` is a (image rows, half columns) float32 buffer.
    """
    rows, cols = window.shape
    image_rows, image_cols = image.shape
    last_col = image_cols - 1
    for r in range(image_rows):
        source = image[r]
        target = scratch[r]
        for x in range(cols):
            far_left = source[max(2 * x - 2, 0)]
            left = source[max(2 * x - 1, 0)]
            right = source[min(2 * x + 2, last_col)]
            far_right = source[min(2 * x + 3, last_col)]
            target[x] = (far_left + far_right + 5.0 * (left + right)
                         + 10.0 * (source[2 * x] + source[2 * x + 1])) * 0.03125
    last_row = image_rows - 1
    for y in range(rows):
        far_above = scratch[max(2 * y - 2, 0)]
        above = scratch[max(2 * y - 1, 0)]
        upper = scratch[2 * y]
        lower = scratch[2 * y + 1]
        below = scratch[min(2 * y + 2, last_row)]
        far_below = scratch[min(2 * y + 3, last_row)]
        block_row = block_out[y]
        target = out[y]
        window_row = window[y]
        for x in range(cols):
            value = (far_above[x] + far_below[x] + 5.0 * (above[x] + below[x])
                     + 10.0 * (upper[x] + lower[x])) * 0.03125
            block_row[x] = value
            target[x] = (value - mean) * window_row[x]


@_jit
def peak_and_sidelobe(surface: np.ndarray, exclusion: int):
    """(row, col, peak value, peak-to-sidelobe ratio) of a periodic correlation surface,
    the sidelobe being everything outside a (2 exclusion + 1)^2 box around the peak."""
    rows, cols = surface.shape
    flat = surface.ravel()
    total = 0.0
    squares = 0.0
    for index in range(flat.size):  # no branch: vectorizes
        value = flat[index]
        total += value
        squares += value * value
    best_index = np.argmax(flat)
    best = flat[best_index]
    best_row, best_col = best_index // cols, best_index % cols
    box_total = 0.0
    box_squares = 0.0
    for dy in range(-exclusion, exclusion + 1):
        for dx in range(-exclusion, exclusion + 1):
            value = surface[(best_row + dy) % rows, (best_col + dx) % cols]
            box_total += value
            box_squares += value * value
    count = rows * cols - (2 * exclusion + 1) ** 2
    mean = (total - box_total) / count
    variance = max((squares - box_squares) / count - mean * mean, 1e-30)
    return best_row, best_col, best, (best - mean) / math.sqrt(variance)


@_jit
def foroosh_offsets(surface: np.ndarray, peak_row: int, peak_col: int):
    """Sub-pixel peak offsets (rows, cols) by Foroosh's neighbour ratio (eq. 21-22):
    with C(s) the larger neighbour (s = +1 or -1), s * C(s) / (C(s) + C(0)), clipped to
    +-0.5, 0 when the neighbours carry no information. Indices wrap around."""
    rows, cols = surface.shape
    centre = surface[peak_row, peak_col]
    offsets = np.zeros(2)
    for axis in range(2):
        if axis == 0:
            before = surface[(peak_row - 1) % rows, peak_col]
            after = surface[(peak_row + 1) % rows, peak_col]
        else:
            before = surface[peak_row, (peak_col - 1) % cols]
            after = surface[peak_row, (peak_col + 1) % cols]
        side, neighbour = (1.0, after) if after >= before else (-1.0, before)
        denominator = neighbour + centre
        if neighbour > 0 and denominator > 0:
            offsets[axis] = min(max(side * neighbour / denominator, -0.5), 0.5)
    return offsets[0], offsets[1]


@_jit
def magnitude_shifted_into(spectrum: np.ndarray, emphasis: np.ndarray, out: np.ndarray) -> None:
    """out = |spectrum| * emphasis, rows fft-shifted (zero frequency mid-height)."""
    rows, cols = spectrum.shape
    half = rows // 2
    for y in range(rows):
        target = out[(y + half) % rows]
        source = spectrum[y]
        weights = emphasis[y]
        for x in range(cols):
            value = source[x]
            target[x] = math.sqrt(value.real * value.real + value.imag * value.imag) * weights[x]


@_jit
def _edge_pair(source, weights, mean, first, last, col_shift, x):
    total = 0.0
    for c in range(2 * x, 2 * x + 2):
        if first <= c < last:
            total += (source[c] - mean) * weights[c - col_shift]
    return total


@_jit
def apodize_halve_into(image: np.ndarray, mean: float, window: np.ndarray, row_shift: int, col_shift: int,
                       scratch: np.ndarray, out: np.ndarray) -> None:
    """out = 2x 2 block means of (image - mean) * window moved by (row_shift, col_shift).

    The window is applied at full resolution, moved by whole full-resolution pixels,
    before halving: so the half-resolution pair weights the same scene to within half
    a full pixel, as at full resolution. ``scratch`` is (image rows, half columns).
    """
    image_rows, image_cols = image.shape
    rows, cols = out.shape
    # Columns where the moved window reaches: [first, last); half-columns fully inside.
    first, last = max(0, col_shift), min(image_cols, image_cols + col_shift)
    inner_first, inner_last = (first + 1) // 2, last // 2
    for r in range(image_rows):
        target = scratch[r]
        wy = r - row_shift
        if wy < 0 or wy >= image_rows or first >= last:
            for x in range(cols):
                target[x] = 0.0
            continue
        source = image[r]
        weights = window[wy]
        # The edge half-columns, and those the window misses (only these few are checked).
        for x in range(0, min(inner_first, cols)):
            target[x] = _edge_pair(source, weights, mean, first, last, col_shift, x)
        for x in range(max(inner_last, 0), cols):
            target[x] = _edge_pair(source, weights, mean, first, last, col_shift, x)
        # The bulk: both pixels of each pair inside the window (row views from 0 vectorize).
        if inner_last > inner_first:
            pixels = source[2 * inner_first:2 * inner_last]
            moved = weights[2 * inner_first - col_shift:2 * inner_last - col_shift]
            pairs = target[inner_first:inner_last]
            for k in range(pairs.shape[0]):
                pairs[k] = (pixels[2 * k] - mean) * moved[2 * k] + (pixels[2 * k + 1] - mean) * moved[2 * k + 1]
    for y in range(rows):
        upper = scratch[2 * y]
        lower = scratch[2 * y + 1]
        target = out[y]
        for x in range(cols):
            target[x] = (upper[x] + lower[x]) * 0.25


@_jit
def normalized_angular_cross_into(current: np.ndarray, reference_conjugates: np.ndarray, ramps: np.ndarray,
                                  accumulator: np.ndarray, out: np.ndarray) -> None:
    """``out[j] = sum_k ramps[k, j] * n(sum_i current[i, j] * reference_conjugates[k, i, j])``
    with ``n(z) = z / |z|``: the normalized angular cross spectra against K references,
    summed over radii, each moved by its ramp, added into one spectrum. Rows are walked
    contiguously (``accumulator``: one row of scratch); numpy's einsum would first make
    the K x radii x frequencies product."""
    radii, frequencies = current.shape
    for j in range(frequencies):
        out[j] = 0.0
    for k in range(reference_conjugates.shape[0]):
        for j in range(frequencies):
            accumulator[j] = 0.0
        for i in range(radii):
            for j in range(frequencies):
                accumulator[j] += current[i, j] * reference_conjugates[k, i, j]
        for j in range(frequencies):
            value = accumulator[j]
            magnitude = max(abs(value), 1e-30)
            out[j] += value / magnitude * ramps[k, j]


@_jit
def kernel_autocovariances(frame: np.ndarray, kernel: int, out: np.ndarray) -> None:
    """For each ``kernel`` x ``kernel`` block of ``frame`` (whole blocks only): out[r, c] =
    (mean, autocovariance at lag 0, at lag 1, at lag 2), the lags averaged over the
    row and column directions and taken within the block, about the block's mean."""
    kernel_rows, kernel_cols = out.shape[0], out.shape[1]
    count = kernel * kernel
    pairs1 = kernel * (kernel - 1)
    pairs2 = kernel * (kernel - 2)
    for block_row in range(kernel_rows):
        top = block_row * kernel
        for block_col in range(kernel_cols):
            left = block_col * kernel
            total = 0.0
            for y in range(top, top + kernel):
                for x in range(left, left + kernel):
                    total += frame[y, x]
            mean = total / count
            zero = along1 = along2 = down1 = down2 = 0.0
            for y in range(top, top + kernel):
                for x in range(left, left + kernel):
                    c = frame[y, x] - mean
                    zero += c * c
                    if x + 1 < left + kernel:
                        along1 += c * (frame[y, x + 1] - mean)
                    if x + 2 < left + kernel:
                        along2 += c * (frame[y, x + 2] - mean)
                    if y + 1 < top + kernel:
                        down1 += c * (frame[y + 1, x] - mean)
                    if y + 2 < top + kernel:
                        down2 += c * (frame[y + 2, x] - mean)
            out[block_row, block_col, 0] = mean
            out[block_row, block_col, 1] = zero / count
            out[block_row, block_col, 2] = (along1 + down1) / (2 * pairs1)
            out[block_row, block_col, 3] = (along2 + down2) / (2 * pairs2)


@_jit
def band_power(spectrum: np.ndarray, band_rows: np.ndarray, weights: np.ndarray) -> float:
    """sum of weights[i, j] |spectrum[band_rows[i], j]|^2 over the band (float64)."""
    total = 0.0
    for i in range(band_rows.size):
        row = band_rows[i]
        for j in range(weights.shape[1]):
            value = spectrum[row, j]
            total += weights[i, j] * (value.real * value.real + value.imag * value.imag)
    return total
