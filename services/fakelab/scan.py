"""What the simulated SEM scans for a request: the request's settings, the preset's
where the request leaves them unset, within what the simulator can render (with a
sample image: what the picture allows, :meth:`SampleImage.check_scan`)."""

from __future__ import annotations

from semservo.messages import ScanRequest
from semservo.simulation.sem import ScanSettings
from semservo.simulation.world import World

#: The magnifications the simulated SEM renders in reasonable time (its scenes are a few
#: hundred micrometres across; at 100x one frame takes seconds, at 1x minutes).
SIMULATED_MAGNIFICATION = (200.0, 200_000.0)


def scan_settings(world: World, request: ScanRequest) -> ScanSettings:
    """The scan a request asks for, or ValueError saying why the simulated SEM cannot
    make it: a magnification outside what it renders, or, with a sample image, a scan
    finer than the picture's detail or wider than the picture allows."""
    preset = world.preset
    if world.sample_image is not None:
        # The picture sets the bounds (SampleImageError is a ValueError, with what to do).
        world.sample_image.check_scan(request.magnification or preset.magnification, request.rows, request.cols)
    else:
        low, high = SIMULATED_MAGNIFICATION
        if request.magnification is not None and not low <= request.magnification <= high:
            raise ValueError(f"the simulated SEM images magnifications {low:g}..{high:g}x, "
                             f"not {request.magnification:g}x")
    return ScanSettings(
        dwell_ns=request.dwell_ns or preset.dwell_ns,
        magnification=request.magnification or preset.magnification,
        rows=request.rows, cols=request.cols,
        working_distance_um=preset.focus_um if request.working_distance_um is None else request.working_distance_um,
        brightness=request.brightness, contrast=request.contrast, bit_depth=request.bit_depth,
        aperture_um=request.aperture_um,
    )
