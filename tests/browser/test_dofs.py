"""Fields of a degree of freedom show only for a run that servoes it; the Position panel
shows a servoing run's own settings; a teach with tilts shows its focus sweep's
progress, then the depth map with its colour scale, and a five-DOF run every angle."""

from __future__ import annotations

import re

import pytest
from playwright.sync_api import expect

from tests.browser.test_layout import assert_holds

pytestmark = pytest.mark.integration

ALL = ["x", "y", "rotation", "alpha", "beta"]


def test_fields_follow_the_runs_degrees_of_freedom(open_page, lab):
    page = open_page(1280)
    lab.teach(frames=2)
    # A run started elsewhere (a script): the page shows what it servoes and its settings.
    run = lab.start(dofs=["x", "y", "gamma"], tolerance_px=0.05, max_iterations=600, hold=True, resume=True)
    try:
        expect(page.locator("#run-id")).to_have_text(run.run_id, timeout=10_000)
        expect(page.locator("#readout-gamma")).to_be_visible()
        expect(page.locator("#readout-alpha")).to_be_hidden()
        expect(page.locator("#angles-panel")).to_be_visible()
        expect(page.locator("#max-iterations")).to_have_value("600")
        expect(page.locator("#tolerance")).to_have_value("0.05")
        expect(page.locator("#hold")).to_be_checked()
        expect(page.locator("input[name=dof][value=rotation]")).to_be_checked()
        expect(page.locator("input[name=dof][value=alpha]")).not_to_be_checked()
        expect(page.locator("#position-note")).to_contain_text(run.run_id)
        page.wait_for_function("document.querySelectorAll('#plot-angles .u-legend .u-series').length === 2")
        assert_holds(page, ["x", "y", "rotation"])
    finally:
        lab.stop("the test has seen enough")
    run = lab.start(dofs=["x", "y"], tolerance_px=0.05, max_iterations=77, hold=True, resume=True)
    try:
        expect(page.locator("#run-id")).to_have_text(run.run_id, timeout=10_000)
        expect(page.locator("#max-iterations")).to_have_value("77")
        expect(page.locator("input[name=dof][value=rotation]")).not_to_be_checked()
        expect(page.locator("#readout-gamma")).to_be_hidden()
        expect(page.locator("#angles-panel")).to_be_hidden()
        page.wait_for_function("document.querySelectorAll('#plot-error .u-legend .u-series').length === 3")
        assert_holds(page, ["x", "y"])
    finally:
        lab.stop("the test has seen enough")
        lab.resume()


def test_max_iterations_follow_the_tilt_boxes_until_someone_edits_them(open_page):
    """A run that servoes the tilts acts on every fresh frame while it waits for each
    focus sweep: the form offers the demo's 600 iterations when a tilt is ticked (150 let
    a 5-DOF run on a sparse picture end before it converged), 150 again without, and
    keeps what someone typed."""
    page = open_page(1280)
    expect(page.locator("#max-iterations")).to_have_value("150")
    page.check("input[name=dof][value=alpha]")
    expect(page.locator("#max-iterations")).to_have_value("600")
    page.check("input[name=dof][value=beta]")
    page.uncheck("input[name=dof][value=alpha]")
    expect(page.locator("#max-iterations")).to_have_value("600")  # beta still ticked
    page.uncheck("input[name=dof][value=beta]")
    expect(page.locator("#max-iterations")).to_have_value("150")
    page.fill("#max-iterations", "77")
    page.check("input[name=dof][value=alpha]")
    expect(page.locator("#max-iterations")).to_have_value("77")
    page.uncheck("input[name=dof][value=alpha]")


@pytest.fixture
def tilts_preset(system, lab):
    """The simulated lab in its small-depth-of-field preset (focus can see tilts), and
    back to the preset it was in afterwards, its frames flowing again before the next
    test teaches on them."""
    from semservo.config import connect
    from semservo.transport import ControlClient
    from tests.integration.helpers import wait_for

    fakelab = ControlClient(connect("127.0.0.1", system["settings"].fakelab.control_port), timeout_s=10, retries=1)
    before = fakelab.request("info")["preset"]
    fakelab.request("set_preset", preset="tilts")
    try:
        yield
    finally:
        fakelab.request("set_preset", preset=before["name"])
        fakelab.close()
        seen = lab.status().latest_frame_seq or 0
        wait_for(lambda: (status := lab.status()).frame_acquisition.get("magnification") == before["magnification"]
                 and (status.latest_frame_seq or 0) > seen + 2, 60, "frames at the restored preset")


def test_a_teach_with_tilts_shows_its_sweep_then_a_five_dof_run_every_angle(open_page, lab, tilts_preset):
    lab.resume()
    page = open_page(1280)
    expect(page.locator("#live-acquisition")).to_contain_text("×3000", timeout=20_000)
    page.fill("#teach-frames", "2")
    page.check("#teach-tilts")
    page.click("#teach-live")
    # The teach answers at once; the sweep's progress is shown as it scans, then its end.
    expect(page.locator("#tilt-teach-text")).to_contain_text(re.compile(r"\d+ of \d+ frames scanned"), timeout=20_000)
    expect(page.locator("#tilt-teach-progress")).to_be_visible()
    expect(page.locator("#tilt-teach-text")).to_contain_text("focus sweep done", timeout=120_000)
    expect(page.locator("#tilt-teach-progress")).to_be_hidden()
    expect(page.locator("#tilt-summary")).to_contain_text("taught plane α")
    # A five-DOF run a script starts, kept alive through a transient the test is not
    # about (no divergence or stall rule ends it while the test looks).
    run = lab.start(dofs=ALL, max_iterations=600, hold=True, diverge_factor=1e6, diverge_iterations=1000,
                    stall_after=100_000)
    try:
        expect(page.locator("#run-id")).to_have_text(run.run_id, timeout=10_000)
        expect(page.locator("#state")).to_have_text("servoing", timeout=10_000)
        for readout in ("gamma", "alpha", "beta"):
            expect(page.locator(f"#readout-{readout}")).to_be_visible()
        # The tilts a focus sweep measured reach the header and the angle plot.
        try:
            expect(page.locator("#alpha")).not_to_have_text("–", timeout=60_000)
        except AssertionError as error:  # say where the run stood: the page alone does not
            status, record = lab.status(), lab.run(run.run_id)
            actions = [(r.get("action"), r.get("tilt_action"), r.get("alpha_deg")) for r in record.trajectory][-20:]
            raise AssertionError(f"no tilt reached the header: the run is {status.state} ({status.reason}); "
                                 f"its last iterations {actions}") from error
        page.wait_for_function("window.semservo.series && window.semservo.series.angle.alpha.some((v) => v !== null)",
                               timeout=30_000)
        page.wait_for_function("document.querySelectorAll('#plot-angles .u-legend .u-series').length === 4")
        # The run's sweep: its depth map with a colour scale on the page, not in a tooltip.
        expect(page.locator("#depth-map")).to_be_visible(timeout=10_000)
        expect(page.locator("#depth-max")).to_have_text(re.compile(r"^\+\d+\.\d+$"))
        expect(page.locator("#depth-min")).to_have_text(re.compile(r"^−\d+\.\d+$"))
        expect(page.locator(".colour-scale")).to_contain_text("nearer")
        expect(page.locator(".colour-scale .gradient")).to_be_visible()
        expect(page.locator("#max-iterations")).to_have_value("600")
        assert_holds(page, ALL)
    finally:
        lab.stop("the test has seen enough")
        lab.resume()
