"""What a user would call a broken page, measured in the browser: element boxes that
overlap another panel or leave their own, a page wider than the window, a label or a
button broken over two lines, a broken image, a field shown for a degree of freedom
the run does not servo. Each returns the problems in words (an empty list: none)."""

from __future__ import annotations

# Boxes in page coordinates. A panel: the header, each image, each control panel, each
# plot, the runs (data-panel names them; the classes find them in older pages too). An element inside a scroll container
# (overflow auto or scroll) counts only where it can be seen; one inside overflow: hidden
# counts whole, since what is cut off is lost to the user.
LAYOUT_JS = r"""
() => {
  const problems = [];
  const shown = (el) => {
    if (el.getClientRects().length === 0) return false;
    const style = getComputedStyle(el);
    if (style.visibility === "hidden" || Number(style.opacity) === 0) return false;
    if (el.closest(".visually-hidden")) return false;
    const box = el.getBoundingClientRect();
    return box.width >= 1 && box.height >= 1;
  };
  const page = (r) => ({ left: r.left + scrollX, top: r.top + scrollY, right: r.right + scrollX, bottom: r.bottom + scrollY });
  const clip = (r, c) => ({ left: Math.max(r.left, c.left), top: Math.max(r.top, c.top),
                            right: Math.min(r.right, c.right), bottom: Math.min(r.bottom, c.bottom) });
  const empty = (r) => r.right - r.left < 1 || r.bottom - r.top < 1;
  const TOLERANCE = 1;  // px: sub-pixel rounding
  const overlap = (a, b) => a.left < b.right - TOLERANCE && b.left < a.right - TOLERANCE
    && a.top < b.bottom - TOLERANCE && b.top < a.bottom - TOLERANCE;
  const within = (a, b) => a.left >= b.left - TOLERANCE && a.top >= b.top - TOLERANCE
    && a.right <= b.right + TOLERANCE && a.bottom <= b.bottom + TOLERANCE;
  const describe = (el) => {
    let text = el.tagName.toLowerCase();
    if (el.id) text += `#${el.id}`;
    else if (typeof el.className === "string" && el.className.trim()) text += `.${el.className.trim().split(/\s+/).join(".")}`;
    const words = (el.textContent || "").trim().replace(/\s+/g, " ").slice(0, 30);
    return words ? `${text} ("${words}")` : text;
  };
  // What the user can see of an element: clipped by the scroll containers it is in.
  const visibleBox = (el, panel) => {
    let box = page(el.getBoundingClientRect());
    for (let parent = el.parentElement; parent && parent !== panel; parent = parent.parentElement) {
      const style = getComputedStyle(parent);
      if (/(auto|scroll)/.test(style.overflowX + style.overflowY)) box = clip(box, page(parent.getBoundingClientRect()));
    }
    return box;
  };

  if (document.documentElement.scrollWidth > innerWidth + TOLERANCE) {
    problems.push(`the page is ${document.documentElement.scrollWidth} px wide in a ${innerWidth} px window`);
  }
  const PANELS = "[data-panel], header, figure, .panel, .plot, .history";
  const panels = [...document.querySelectorAll(PANELS)].filter(shown);
  const named = (panel) => panel.dataset.panel || describe(panel).split(" (")[0];
  const boxes = panels.map((panel) => page(panel.getBoundingClientRect()));
  panels.forEach((a, i) => panels.forEach((b, j) => {
    if (j > i && !a.contains(b) && !b.contains(a) && overlap(boxes[i], boxes[j])) problems.push(`panel ${named(a)} overlaps panel ${named(b)}`);
  }));
  panels.forEach((panel, i) => {
    const reported = [];  // the outermost element that is out of place, not each of its children
    for (const el of panel.querySelectorAll("*")) {
      if (el.closest(PANELS) !== panel || !shown(el) || reported.some((bad) => bad.contains(el))) continue;
      const box = visibleBox(el, panel);
      if (empty(box)) continue;
      if (!within(box, boxes[i])) {
        problems.push(`${describe(el)} leaves its panel ${named(panel)}`);
        reported.push(el);
        continue;
      }
      panels.forEach((other, j) => {
        if (j !== i && !panel.contains(other) && !other.contains(panel) && overlap(box, boxes[j])) {
          problems.push(`${describe(el)} of ${named(panel)} overlaps panel ${named(other)}`);
          reported.push(el);
        }
      });
    }
    // One line each: a label or a button broken over two lines reads as two things.
    for (const el of panel.querySelectorAll("label, button, .file-button, th")) {
      if (el.closest(PANELS) !== panel || !shown(el)) continue;
      const lines = new Set([...el.getClientRects()].map((r) => Math.round(r.top))).size;
      const style = getComputedStyle(el);
      const lineHeight = parseFloat(style.lineHeight) || 1.3 * parseFloat(style.fontSize);
      const height = el.getBoundingClientRect().height - parseFloat(style.paddingTop) - parseFloat(style.paddingBottom)
        - parseFloat(style.borderTopWidth) - parseFloat(style.borderBottomWidth);
      if (lines > 1 || height > 1.8 * lineHeight) problems.push(`${describe(el)} in ${named(panel)} wraps`);
      if (el.scrollWidth > el.clientWidth + TOLERANCE && style.display !== "inline") {
        problems.push(`${describe(el)} in ${named(panel)} is cut off`);
      }
    }
  });
  return problems;
}
"""

BROKEN_IMAGES_JS = r"""
() => [...document.querySelectorAll("img")]
  .filter((img) => img.getClientRects().length > 0 && getComputedStyle(img).visibility !== "hidden")
  .filter((img) => !img.complete || img.naturalWidth === 0)
  .map((img) => `${img.id || img.alt || img.src}: a broken image (src ${img.getAttribute("src")})`)
"""

# Which degrees of freedom a visible element speaks of: data-dofs, or a plot legend's
# label (e_x, γ, α, β ...).
DOF_FIELDS_JS = r"""
(dofs) => {
  const problems = [];
  const shown = (el) => el.getClientRects().length > 0;
  for (const el of document.querySelectorAll("[data-dofs]")) {
    const wanted = el.dataset.dofs.split(" ").some((dof) => dofs.includes(dof));
    if (shown(el) !== wanted) {
      problems.push(`${el.id || el.dataset.panel} (${el.dataset.dofs}) is ${shown(el) ? "shown" : "hidden"} for a run of ${dofs.join(", ")}`);
    }
  }
  // The header's readout: a symbol of a DOF the run does not servo.
  const symbols = { "γ": "rotation", "α": "alpha", "β": "beta" };
  for (const span of document.querySelectorAll("header .readout > *")) {
    if (!shown(span)) continue;
    for (const [symbol, dof] of Object.entries(symbols)) {
      if (span.textContent.includes(symbol) && !dofs.includes(dof)) problems.push(`the header shows ${symbol} for a run of ${dofs.join(", ")}`);
    }
  }
  const legend = { "e_x": "x", "e_y": "y", "γ": "rotation", "α": "alpha", "β": "beta", "e_rot": "rotation" };
  for (const label of document.querySelectorAll(".u-legend .u-series .u-label")) {
    if (!shown(label)) continue;
    const text = label.textContent.trim();
    for (const [prefix, dof] of Object.entries(legend)) {
      if (text.startsWith(prefix) && !dofs.includes(dof)) problems.push(`the plot legend shows ${text} for a run of ${dofs.join(", ")}`);
    }
  }
  return problems;
}
"""


def layout_problems(page) -> list[str]:
    return page.evaluate(LAYOUT_JS)


def broken_images(page) -> list[str]:
    return page.evaluate(BROKEN_IMAGES_JS)


def dof_problems(page, dofs: list[str]) -> list[str]:
    return page.evaluate(DOF_FIELDS_JS, dofs)
