"""Stored targets on the dashboard: save the taught reference under a name, see it
listed with its thumbnail, export it, delete it, import it back, go to it; every
refusal said in words."""

from __future__ import annotations

import re

import pytest
from playwright.sync_api import expect

pytestmark = pytest.mark.integration

NAME = "bond pad 3"


def test_stored_targets_from_the_dashboard(open_page, lab, tmp_path):
    lab.resume()
    page = open_page(1280)
    before = page.inner_text("#reference-id")
    page.click("#teach-live")
    expect(page.locator("#reference-id")).not_to_have_text(before)
    item = page.locator(f"#targets li[data-target='{NAME}']")
    try:
        page.fill("#target-name", NAME)
        page.fill("#target-note", "left of the crack")
        page.click("#target-save-button")
        expect(item).to_contain_text("left of the crack")
        page.wait_for_function("(name) => [...document.querySelectorAll('#targets li')].some((li) => "
                               "li.dataset.target === name && li.querySelector('img').naturalWidth > 0)", arg=NAME)
        # The same name again: asked before replacing; declined, the refusal in words.
        page.fill("#target-name", NAME)
        page.fill("#target-note", "left of the crack, again")
        page.once("dialog", lambda dialog: dialog.dismiss())
        page.click("#target-save-button")
        expect(page.locator("#message-text")).to_contain_text("exists")
        page.once("dialog", lambda dialog: dialog.accept())
        page.click("#target-save-button")
        expect(page.locator("#target-name")).to_have_value("")  # saved: the form is cleared
        expect(item).to_have_count(1)
        expect(item).to_contain_text("left of the crack, again")

        # Exported as one file, deleted (asked first), imported back from that file.
        with page.expect_download() as download:
            item.locator("a.export").click()
        assert download.value.suggested_filename == f"{NAME}.semservo-target.tif"
        exported = tmp_path / "exported.tif"
        download.value.save_as(exported)
        assert exported.read_bytes()[:4] in (b"II*\x00", b"MM\x00*")
        page.once("dialog", lambda dialog: dialog.accept())
        item.locator("button.delete").click()
        expect(item).to_have_count(0)
        page.set_input_files("#target-import", str(exported))
        expect(item).to_contain_text("left of the crack, again")
        bad = tmp_path / "notes.tif"
        bad.write_bytes(b"these are notes, not a target")
        page.set_input_files("#target-import", str(bad))
        expect(page.locator("#message-text")).to_contain_text("not a semservo target file")

        # Go: the stored pose, its reference, a run towards it (the client's tests follow
        # such a run to its end).
        before = page.inner_text("#run-id")
        item.locator("button.go").click()
        expect(page.locator("#run-id")).not_to_have_text(before, timeout=10_000)
        expect(page.locator("#reference-id")).to_contain_text(f"(target {NAME})")
        expect(page.locator("#state")).to_have_text(re.compile("servoing|converged"))
        assert lab.run(page.inner_text("#run-id")).reference_id == lab.reference().id
    finally:
        lab.stop("the test has seen enough")
        lab.resume()
        if any(target.name == NAME for target in lab.targets()):
            lab.delete_target(NAME)
