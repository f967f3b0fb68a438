"""The dashboard in a real browser, as a user sees it."""

from __future__ import annotations

import os
import re
import signal

import pytest
from playwright.sync_api import expect

pytestmark = pytest.mark.integration

CONVERGED_S = 90_000  # ms: a run at 20x simulated speed converges in well under this


def image_width(page, selector: str) -> int:
    return page.eval_on_selector(selector, "img => img.complete ? img.naturalWidth : 0")


def teach(page) -> str:
    before = page.inner_text("#reference-id")
    page.click("#teach-live")
    expect(page.locator("#reference-id")).not_to_have_text(before)
    return page.inner_text("#reference-id")


def test_the_page_shows_the_live_frame_state_and_every_service(page):
    expect(page).to_have_title("semservo")
    expect(page.locator("#state")).to_have_text(re.compile("idle|converged|stopped|failed"))
    page.wait_for_function("document.getElementById('live').naturalWidth === 512")
    seq = page.inner_text("#live-seq")
    # What the frames say of their acquisition (the simulated SEM knows its pixel size and dwell).
    expect(page.locator("#live-acquisition")).to_contain_text(re.compile(r"\d+\.\d+ nm/px · ×\d+ · \d+ ns/px"))
    page.wait_for_function(f"document.getElementById('live-seq').textContent !== {seq!r}")  # frames keep coming
    for name in ("fakelab", "imageserver", "estimator", "stage", "controller"):
        expect(page.locator(f"#services li[data-service={name}] .up")).to_be_visible()
    expect(page.locator("#banner")).to_be_hidden()
    expect(page.locator("#stop")).to_be_visible()
    assert not page.errors


def test_a_double_click_on_teach_teaches_once(page):
    """The second click of a double click lands while the first teach is out: the button
    takes it no further (the gateway would refuse a second teach meanwhile, 409)."""
    teaches = []
    page.on("request", lambda request: teaches.append(request.url)
            if request.method == "POST" and "/teach" in request.url else None)
    before = page.inner_text("#reference-id")
    page.dblclick("#teach-live")
    expect(page.locator("#reference-id")).not_to_have_text(before)
    expect(page.locator("#teach-live")).not_to_have_attribute("aria-busy", "true")
    assert len(teaches) == 1, teaches
    expect(page.locator("#message")).to_be_hidden()
    assert not page.errors


def test_jog_moves_the_stage_readout(page):
    page.wait_for_function("document.getElementById('stage-x').textContent !== '–'")
    before = float(page.inner_text("#stage-x"))
    page.fill("#jog-step", "3")
    page.click("#jog-x-plus")
    page.wait_for_function(f"Math.abs(parseFloat(document.getElementById('stage-x').textContent) - {before} - 3) < 0.01")
    page.click("#jog-x-minus")
    page.wait_for_function(f"Math.abs(parseFloat(document.getElementById('stage-x').textContent) - {before}) < 0.01")


def test_teach_start_converge_and_the_plots_fill(page):
    reference = teach(page)
    assert reference.startswith("frame ")
    page.wait_for_function("document.getElementById('reference').naturalWidth === 512")
    page.wait_for_function("document.getElementById('difference').naturalWidth === 512")
    page.fill("#jog-step", "4")
    page.click("#jog-x-plus")
    page.click("#jog-y-minus")
    page.wait_for_timeout(500)
    page.click("#start")
    # The position law can arrive between two polls of the page: servoing may not be seen.
    expect(page.locator("#state")).to_have_text(re.compile("servoing|converged"), timeout=10_000)
    expect(page.locator("#state")).to_have_text("converged", timeout=CONVERGED_S)
    points = int(page.inner_text("#error-points").split()[0])
    assert points >= 2
    assert int(page.inner_text("#voltage-points").split()[0]) == points
    # The plotted error ends near zero: what the user reads off the plot's data.
    last = page.evaluate("() => { const s = window.semservo.series.translation; return [s.x.at(-1), s.y.at(-1)]; }")
    assert abs(last[0]) < 0.5 and abs(last[1]) < 0.5
    # The header's error: the mean the controller judged, under the tolerance.
    page.wait_for_function("parseFloat(document.getElementById('error-px').textContent) <= 0.1", timeout=5_000)
    run_id = page.inner_text("#run-id")
    expect(page.locator(f"#runs tr[data-run-id='{run_id}'] td.outcome-converged")).to_be_visible(timeout=10_000)


def test_stop_a_run_midway(page):
    teach(page)
    for step in ("", "50"):  # empty sent 0; over the field's 20 went out as it was
        page.fill("#jog-step", step)
        page.click("#jog-x-plus")
        expect(page.locator("#message-text")).to_contain_text("jog step (µm): a number from 0.01 to 20")
    page.fill("#jog-step", "9")
    page.click("#jog-x-plus")
    page.click("#jog-y-plus")
    page.fill("#tolerance", "0.01")
    page.fill("#max-iterations", "10000")
    page.wait_for_timeout(300)
    before = page.inner_text("#run-id")
    page.click("#start")
    # The new run, servoing (the last run's iteration count would satisfy a wait on the
    # count alone, and a stop pressed before the start arrives rightly refuses the start).
    expect(page.locator("#run-id")).not_to_have_text(before, timeout=10_000)
    expect(page.locator("#state")).to_have_text("servoing", timeout=10_000)
    page.wait_for_function("parseInt(document.getElementById('iteration').textContent) >= 1", timeout=30_000)
    page.click("#stop")
    expect(page.locator("#state")).to_have_text("stopped", timeout=10_000)
    expect(page.locator("#stage-state")).to_contain_text("stopped")
    run_id = page.inner_text("#run-id")
    # The stage refuses jogs until resumed, and says so in words.
    page.click("#jog-x-minus")
    expect(page.locator("#message-text")).to_contain_text("stopped")
    page.click("#resume")
    expect(page.locator("#message")).to_be_hidden()  # the refusal does not outlive a later action's success
    expect(page.locator("#stage-state")).to_have_text("ready")
    expect(page.locator("#resume")).to_be_hidden()
    page.click("#refresh-runs")
    expect(page.locator(f"#runs tr[data-run-id='{run_id}'] td.outcome-stopped")).to_be_visible(timeout=10_000)


def test_open_a_run_from_the_history(page):
    page.click("#refresh-runs")
    row = page.locator("#runs tr").first
    expect(row).to_be_visible(timeout=10_000)
    run_id = row.get_attribute("data-run-id")
    row.click()
    expect(page.locator("#detail-id")).to_have_text(run_id)
    expect(page.locator("#detail-summary")).to_contain_text("iterations")
    assert page.get_attribute("#detail-csv", "href") == f"/runs/{run_id}.csv"
    # The report: 1000 px wide for an x, y run, wider with a panel of angles.
    page.wait_for_function("document.getElementById('detail-report').naturalWidth >= 1000")
    with page.expect_download() as download:
        page.click("#detail-csv")
    assert download.value.suggested_filename == f"{run_id}.csv"


def test_teach_from_a_clicked_mask(page):
    page.check("input[name=click-mode][value=mask]")
    box = page.locator("#live").bounding_box()
    for fx, fy in ((0.3, 0.3), (0.7, 0.32), (0.68, 0.7), (0.32, 0.68)):
        page.mouse.click(box["x"] + fx * box["width"], box["y"] + fy * box["height"])
    expect(page.locator("#mask-count")).to_have_text("4")
    points = page.get_attribute("#mask-polygon", "points").split()
    assert len(points) == 4
    page.click("#teach-mask")
    expect(page.locator("#reference-id")).to_have_text(re.compile("^mask "))
    expect(page.locator("#mask-count")).to_have_text("0")


def test_click_to_move_and_an_api_error_in_words(page):
    page.check("input[name=click-mode][value=move]")
    page.wait_for_function("document.getElementById('stage-x').textContent !== '–'")
    before = float(page.inner_text("#stage-x"))
    box = page.locator("#live").bounding_box()
    page.mouse.click(box["x"] + 0.6 * box["width"], box["y"] + 0.5 * box["height"])  # 51 px right of centre
    page.wait_for_function(f"Math.abs(parseFloat(document.getElementById('stage-x').textContent) - {before}) > 5")
    # A request the API refuses is shown to the user, naming the field.
    page.fill("#tolerance", "-1")
    page.click("#start")
    expect(page.locator("#message")).to_be_visible()
    expect(page.locator("#message-text")).to_contain_text("tolerance_px")


def test_a_tilt_run_without_a_taught_sweep_says_what_to_do(page):
    expect(page.locator("#tilt-panel")).to_be_visible()
    expect(page.locator("#teach-tilts")).to_be_visible()
    teach(page)  # the live frame, without its focus sweep
    page.check("input[name=dof][value=alpha]")
    page.check("input[name=dof][value=beta]")
    page.click("#start")
    expect(page.locator("#message")).to_be_visible()
    expect(page.locator("#message-text")).to_contain_text("teach with tilts=true")
    page.uncheck("input[name=dof][value=alpha]")
    page.uncheck("input[name=dof][value=beta]")
    page.click("#message-close")


def test_teach_from_an_uploaded_image(page, system, tmp_path):
    import httpx

    frame = httpx.get(system["url"] + "/frames/latest.png").content
    path = tmp_path / "target.png"
    path.write_bytes(frame)
    page.set_input_files("#teach-file", str(path))
    expect(page.locator("#reference-id")).to_have_text(re.compile("^image "))
    # A file that is no image is refused, in words, and the reference stays.
    bad = tmp_path / "notes.png"
    bad.write_bytes(b"these are not pixels")
    page.set_input_files("#teach-file", str(bad))
    expect(page.locator("#message-text")).to_contain_text("not a readable PNG/TIFF")
    expect(page.locator("#reference-id")).to_have_text(re.compile("^image "))


def test_a_pulled_serial_cable_shows_a_banner(page, system):
    from semservo.config import connect
    from semservo.transport import ControlClient

    fakelab = ControlClient(connect("127.0.0.1", system["settings"].fakelab.control_port), timeout_s=5, retries=1)
    try:
        fakelab.request("serial_link", plugged=False)
        expect(page.locator("#banner")).to_contain_text("serial link", timeout=20_000)
        fakelab.request("serial_link", plugged=True)
        expect(page.locator("#banner")).to_be_hidden(timeout=20_000)
    finally:
        fakelab.request("serial_link", plugged=True)
        fakelab.close()


def test_a_dead_service_shows_a_banner(page, system):
    launcher = system["launcher"]
    os.kill(launcher.health("estimator").pid, signal.SIGKILL)
    expect(page.locator("#banner")).to_contain_text("estimator is down", timeout=15_000)
    expect(page.locator("#services li[data-service=estimator] .down")).to_be_visible()
    launcher.restart_service("estimator")
    expect(page.locator("#banner")).to_be_hidden(timeout=15_000)
