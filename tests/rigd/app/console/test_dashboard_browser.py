"""The dashboard in a real browser against the sim rig: live views, start/stop, the take list."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from rigd.app.testing.console import ConsoleDaemon
from tests.rigd.app.console.browser import chromium_page

DEVICES = ("cam0", "cam1", "cam2", "ev0", "ev1")

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]


def test_dashboard_live_views_start_stop_and_take_list(
    console_daemon: Callable[..., ConsoleDaemon], tmp_path: Path
) -> None:
    from playwright.sync_api import expect

    cd = console_daemon()
    with chromium_page() as page:
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        # Without the login, the browser gets the page that says how to log in, and nothing else.
        page.goto(cd.url)
        expect(page.get_by_test_id("login-needed")).to_contain_text("rigd console-url")
        # The operator opens the login URL (`rigd console-url`); it lands on a clean address.
        page.goto(cd.login_url)
        assert page.url == cd.url
        expect(page.get_by_test_id("state")).to_have_text("idle")
        page.get_by_test_id("take-name").fill("browser-take")
        page.get_by_test_id("take-notes").fill("started by the browser test")
        page.get_by_test_id("start").click()
        expect(page.get_by_test_id("state")).to_have_text("capturing")
        expect(page.get_by_test_id("take-msg")).to_contain_text("recording")
        # Every view shows a preview, then a newer one: all five are live.
        for dev in DEVICES:
            tile = f'[data-testid="view-{dev}"]'
            page.wait_for_function(f"document.querySelector('{tile}').dataset.version !== '0'")
            first = page.eval_on_selector(tile, "e => e.dataset.version")
            page.wait_for_function(f"document.querySelector('{tile}').dataset.version !== '{first}'")
            expect(page.locator(tile)).to_contain_text("rate")
        expect(page.get_by_test_id("trigger")).to_contain_text("Hz")
        page.get_by_test_id("event-window").select_option("40")
        page.wait_for_function("fetch('/api/status').then(r => r.json()).then(d => d.event_window_ms === 40)")
        page.screenshot(path=str(tmp_path / "console-dashboard.png"), full_page=True)
        page.get_by_test_id("stop").click()
        expect(page.get_by_test_id("state")).to_have_text("idle")
        row = page.locator('[data-testid="take-row"][data-status="complete"]', has_text="browser-take")
        expect(row).to_have_count(1)
        expect(row).to_contain_text("started by the browser test")
        expect(row.locator("img")).to_have_count(3)
        expect(row.locator("canvas")).to_have_count(2)
        page.screenshot(path=str(tmp_path / "console-takes.png"), full_page=True)
        # During the next take the finished take keeps its event-rate curves (they once vanished
        # whenever the list was rebuilt during a take).
        page.get_by_test_id("take-name").fill("second")
        page.get_by_test_id("start").click()
        expect(page.get_by_test_id("state")).to_have_text("capturing")
        page.wait_for_function("document.querySelectorAll('[data-testid=take-row]').length >= 2")
        expect(row.locator("canvas")).to_have_count(2)
        page.get_by_test_id("stop").click()
        expect(page.get_by_test_id("state")).to_have_text("idle")
        expect(row.locator("canvas")).to_have_count(2)
        assert errors == [], errors
    takes = list(cd.config.service.take_dir.glob("*browser-take*.h5"))
    assert len(takes) == 1
