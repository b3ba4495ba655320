"""The "Send a new link" button an unverified account sees, in the banner on every page and on
the Account page, is legible: its text colour against the background it is drawn on, as the
browser computes both, reaches WCAG AA's 4.5:1 on a laptop and on a phone."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from server.app import create_app
from server.kit.db import make_engine, session_factory, upgrade
from server.kit.settings import Settings
from testkit.factories import PASSWORD, RecordingQueue, make_user
from tests.web.browser_support import CHROMIUM, CHROMIUM_ARGS, patient, require_chromium, serving

AA_NORMAL_TEXT = 4.5
VIEWPORTS = [{"width": 1280, "height": 800}, {"width": 390, "height": 844}]
BUTTONS = {
    "banner": "main > .notice button.link-button",
    "account page": "dl.facts button.link-button",
}
# The text colour, then each background-color from the element up to the root, as computed.
COLOURS_JS = """el => {
  const backgrounds = [];
  for (let node = el; node; node = node.parentElement) {
    backgrounds.push(getComputedStyle(node).backgroundColor);
  }
  return {text: getComputedStyle(el).color, backgrounds};
}"""
RGBA = re.compile(r"rgba?\(\s*([\d.]+)[,\s]+([\d.]+)[,\s]+([\d.]+)(?:\s*[,/]\s*([\d.]+))?\s*\)")

Colour = tuple[float, float, float]


def parse(css: str) -> tuple[Colour, float]:
    """A computed colour as (r, g, b) in 0..255 and its alpha."""
    found = RGBA.fullmatch(css.strip())
    assert found, f"not a computed rgb() colour: {css!r}"
    r, g, b, a = found.groups()
    return (float(r), float(g), float(b)), 1.0 if a is None else float(a)


def over(top: str, below: Colour) -> Colour:
    """`top` composited over an opaque `below`."""
    rgb, alpha = parse(top)
    return (
        rgb[0] * alpha + below[0] * (1 - alpha),
        rgb[1] * alpha + below[1] * (1 - alpha),
        rgb[2] * alpha + below[2] * (1 - alpha),
    )


def effective_background(backgrounds: list[str]) -> Colour:
    """What the element is drawn on: its ancestors' backgrounds stacked on the white canvas."""
    colour: Colour = (255.0, 255.0, 255.0)
    for css in reversed(backgrounds):
        colour = over(css, colour)
    return colour


def luminance(colour: Colour) -> float:
    """WCAG 2's relative luminance of an sRGB colour."""

    def linear(channel: float) -> float:
        c = channel / 255
        return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4

    r, g, b = (linear(c) for c in colour)
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def contrast(a: Colour, b: Colour) -> float:
    """WCAG 2's contrast ratio, 1 to 21."""
    hi, lo = sorted((luminance(a), luminance(b)), reverse=True)
    return (hi + 0.05) / (lo + 0.05)


def measured(colours: dict[str, Any]) -> float:
    """The contrast of the text colour against what it is drawn on, from COLOURS_JS's answer."""
    background = effective_background(colours["backgrounds"])
    return contrast(over(colours["text"], background), background)


def test_the_contrast_formula_matches_wcags_known_values() -> None:
    assert contrast((0, 0, 0), (255, 255, 255)) == pytest.approx(21.0)
    assert contrast((255, 255, 255), (255, 255, 255)) == pytest.approx(1.0)
    assert contrast((0x76, 0x76, 0x76), (255, 255, 255)) == pytest.approx(4.54, abs=0.01)
    assert effective_background(["rgba(0, 0, 0, 0)", "rgb(238, 248, 241)"]) == (238, 248, 241)
    assert effective_background(["rgba(0, 0, 0, 0.5)"]) == (127.5, 127.5, 127.5)


@pytest.fixture
def served(tmp_path: Path) -> Iterator[str]:
    settings = Settings(dev_mode=True, data_dir=tmp_path / "data", cookie_secure=False)
    settings.data_dir.mkdir(parents=True)
    upgrade(settings.resolved_database_url)
    sessions = session_factory(make_engine(settings.resolved_database_url))
    with sessions() as db:
        make_user(db, "dora", verified=False)
    app = create_app(settings, sessions=sessions, work=RecordingQueue(), background=False)
    with serving(app) as url:
        yield url


@pytest.mark.parametrize("viewport", VIEWPORTS, ids=lambda v: f"{v['width']}px")
def test_the_send_a_new_link_button_reaches_aa_contrast(
    served: str, viewport: dict[str, int]
) -> None:
    require_chromium()
    from playwright.sync_api import expect, sync_playwright

    problems: list[str] = []
    ratios: dict[str, float] = {}
    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = patient(chromium.new_page(viewport=viewport))  # type: ignore[arg-type]
        page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda exc: problems.append(str(exc)))
        page.goto(f"{served}/login")
        page.fill("#login", "dora")
        page.fill("#password", PASSWORD)
        page.click("main form button[type=submit]")
        page.wait_for_url(re.compile(r"/account$"), timeout=60_000)
        for where, selector in BUTTONS.items():
            button = page.locator(selector)
            expect(button).to_be_visible(timeout=60_000)
            expect(button).to_have_text("Send a new link")
            ratios[where] = measured(button.evaluate(COLOURS_JS))
        page.goto(f"{served}/")  # the banner is on every page, not the account page alone
        banner = page.locator(BUTTONS["banner"])
        expect(banner).to_be_visible(timeout=60_000)
        ratios["banner on the home page"] = measured(banner.evaluate(COLOURS_JS))
        chromium.close()
    assert all(ratio >= AA_NORMAL_TEXT for ratio in ratios.values()), ratios
    assert problems == [], problems
