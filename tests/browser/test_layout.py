"""The dashboard holds at 900, 1280 and 1920 px: no panel overlaps another, nothing
leaves its panel, no label wraps, no image is broken, the plots follow their panels as
the window changes, the log axis reads in decades, and without a reference the panels
say so in words (tests/browser/layout.py measures it all in the browser)."""

from __future__ import annotations

import contextlib
import math
import re

import pytest
from playwright.sync_api import expect

from tests.browser.layout import broken_images, dof_problems, layout_problems

pytestmark = pytest.mark.integration

WIDTHS = (900, 1280, 1920)
TARGET = "sample-7_pad-12.the-long-name-of-a-target-without-spaces"
NOTE = ("the bond pad left of the crack, imaged at x1200 before the anneal; come back to it after the anneal "
        "and compare (the reference is the 4-frame average)")

IMAGES_SHOWN = """() => ['live', 'reference', 'difference'].every((id) => {
  const img = document.getElementById(id);
  return !img.hidden && img.complete && img.naturalWidth > 0;
})"""

# Every plot on view is as wide as its panel's plot box (uPlot sized from its container).
PLOT_WIDTHS = """() => Object.entries(window.semservo.plots)
  .filter(([, plot]) => plot && plot.box && plot.box.getClientRects().length > 0)
  .map(([name, plot]) => [name, plot.width, Math.floor(plot.box.getBoundingClientRect().width)])"""
PLOTS_FIT = f"() => ({PLOT_WIDTHS})().every(([, plot, box]) => Math.abs(plot - box) <= 1)"


def assert_holds(page, dofs):
    """No overlap, no broken image, no field of a DOF the run does not servo."""
    page.evaluate("window.scrollTo(0, 0)")
    problems = layout_problems(page) + broken_images(page) + dof_problems(page, dofs)
    assert not problems, "\n".join(problems[:30])
    assert not page.errors


@pytest.fixture(scope="module")
def scene(lab):
    """The page at its fullest: a taught reference, a converged x, y run in the history
    and a stored target with a long name and note."""
    lab.teach(frames=2)
    lab.move(x_um=3.0, y_um=-2.0)
    run = lab.start(dofs=["x", "y"], resume=True)
    record = lab.wait(run.run_id, timeout=120)
    assert record.state == "converged", record.reason
    lab.save_target(TARGET, note=NOTE, replace=True)
    yield {"run_id": run.run_id}
    with contextlib.suppress(Exception):  # already gone
        lab.delete_target(TARGET)


@pytest.mark.parametrize("width", WIDTHS)
def test_the_dashboard_holds_at_every_width(open_page, lab, scene, width):
    page = open_page(width)
    page.wait_for_function(IMAGES_SHOWN)
    # The run's detail and report, the stored target's thumbnail: the page at its fullest.
    row = page.locator(f"#runs tr[data-run-id='{scene['run_id']}']")
    expect(row.locator("td").nth(2)).to_have_text("x y")  # its degrees of freedom
    expect(row.locator("td").nth(5)).to_have_text(re.compile(r"^\d+\.\d s$|^\d+:\d\d min$"))  # its duration
    row.click()
    page.wait_for_function("() => { const r = document.getElementById('detail-report'); "
                           "return !r.hidden && r.naturalWidth > 0; }")
    target = page.locator(f"#targets li[data-target='{TARGET}']")
    expect(target).to_contain_text(NOTE)
    page.wait_for_function("(name) => [...document.querySelectorAll('#targets li')].some((li) => "
                           "li.dataset.target === name && li.querySelector('img').naturalWidth > 0)", arg=TARGET)
    # A scale bar on each image, from the frame's pixel size.
    for name in ("live", "reference", "difference"):
        expect(page.locator(f"#{name}-scale .label")).to_have_text(re.compile(r"^\d+ (nm|µm|mm)$"))
    page.wait_for_function(PLOTS_FIT)
    assert_holds(page, lab.status().dofs)


def test_plots_follow_the_window_as_it_is_resized(open_page, lab, scene):
    page = open_page(1920)
    page.wait_for_function(IMAGES_SHOWN)
    page.wait_for_function(PLOTS_FIT)
    wide = dict((name, width) for name, width, _ in page.evaluate(PLOT_WIDTHS))
    for width in (900, 1280):
        page.set_viewport_size({"width": width, "height": 1000})
        page.wait_for_function(PLOTS_FIT)
        assert_holds(page, lab.status().dofs)
    narrow = dict((name, width) for name, width, _ in page.evaluate(PLOT_WIDTHS))
    assert all(narrow[name] != wide[name] for name in wide), (wide, narrow)


def test_the_cost_axis_reads_in_decades_without_minor_lines(page):
    """The log axis's ticks: one per decade (1, 2, 5 within a range of two decades or
    fewer), labelled as a person reads them, the axis as wide as its widest label."""
    splits = page.evaluate("logSplits(null, 1, 1e-4, 1e4)")
    assert splits == pytest.approx([10.0 ** k for k in range(-4, 5)], rel=1e-9)
    labels = page.evaluate("[1e-4, 1e-3, 0.01, 0.1, 1, 10, 100, 1000, 1e4, 2e5].map(logLabel)")
    assert labels == ["1e-4", "1e-3", "0.01", "0.1", "1", "10", "100", "1000", "1e4", "2×1e5"]
    assert page.evaluate("logSplits(null, 1, 0.1, 10)") == pytest.approx([0.1, 0.2, 0.5, 1, 2, 5, 10])
    # The axis is wide enough for "10000" with room to spare (the label was clipped to "0,000").
    assert page.evaluate("axisSize(null, ['10000', '1e-3']) > measure.measureText('10000').width + 10")
    # Cost over eight decades on the real plot: labelled ticks, none a minor one.
    page.evaluate("""() => {
        const plot = window.semservo.plots.cost;
        plot.setData([[1, 2, 3, 4, 5], [5e3, 40, 0.5, 2e-3, 3e-4]]);
    }""")
    drawn = page.evaluate("""() => {
        const plot = window.semservo.plots.cost, scale = plot.scales.y;
        const splits = logSplits(plot, 1, scale.min, scale.max);
        return { splits, labels: logValues(plot, splits) };
    }""")
    assert all(abs(math.log10(value) - round(math.log10(value))) < 1e-9 for value in drawn["splits"]), drawn
    assert len([label for label in drawn["labels"] if label]) >= 3, drawn
    # Voltages whose new labels need more room than the last ones ("37.5" after "35"): the
    # plot is laid out again, its y axis as wide as its labels (uPlot drew "7.5" before).
    page.evaluate("() => window.semservo.plots.voltage.setData([[1, 2], [35, 36], [36, 40]])")
    page.wait_for_timeout(200)
    page.evaluate("() => window.semservo.plots.voltage.setData([[1, 2, 3, 4], [37.1, 37.3, 37.2, 37.2], "
                  "[37.5, 37.9, 37.8, 37.8]])")
    page.wait_for_function("() => { const plot = window.semservo.plots.voltage;"
                           " return plot.axes[1]._values.some((label) => label.includes('.'))"
                           " && plot.bbox.left / devicePixelRatio >= plot.yAxisSize; }", timeout=5000)
    # ... and then it rests: no draw after the layout, with data or without (a plot
    # emptied for a new run, its axis hidden, once redrew 200 times a second).
    page.evaluate("() => { window.voltageDraws = 0;"
                  " window.semservo.plots.voltage.hooks.draw.push(() => { window.voltageDraws += 1; }); }")
    for data in ("[[1, 2, 3, 4], [37.1, 37.3, 37.2, 37.2], [37.5, 37.9, 37.8, 37.8]]", "[[], [], []]"):
        page.evaluate(f"() => window.semservo.plots.voltage.setData({data})")
        page.wait_for_timeout(300)
        settled = page.evaluate("() => window.voltageDraws")
        page.wait_for_timeout(500)
        assert page.evaluate("() => window.voltageDraws") == settled, data


def test_without_a_reference_the_panels_say_so(open_page, system, lab):
    """After the estimator restarts it holds no reference: the Reference and Difference
    panels say so in words (no broken image), the caption names none, and a new teach
    brings the images back."""
    page = open_page(900)
    lab.teach(frames=1)
    page.wait_for_function(IMAGES_SHOWN)
    system["launcher"].restart_service("estimator")
    expect(page.locator("#reference-id")).to_have_text("none taught", timeout=20_000)
    expect(page.locator("#reference-placeholder")).to_be_visible()
    expect(page.locator("#reference-placeholder")).to_contain_text("no reference")
    expect(page.locator("#difference-placeholder")).to_contain_text("no reference")
    expect(page.locator("#reference")).to_be_hidden()
    expect(page.locator("#difference")).to_be_hidden()
    expect(page.locator("#reference-scale")).to_be_hidden()
    assert_holds(page, lab.status().dofs)
    page.click("#teach-live")
    page.wait_for_function(IMAGES_SHOWN)
    expect(page.locator("#reference-placeholder")).to_be_hidden()
    expect(page.locator("#reference-id")).to_have_text(re.compile("^frame "))
