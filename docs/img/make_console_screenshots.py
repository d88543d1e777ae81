"""Screenshots of the web console for docs/console.md and the README (docs/img/console-*.png).

    python docs/img/make_console_screenshots.py [--out docs/img]

Starts the daemon with its console on the sim rig (320x180, private endpoints, a temporary take
directory), logs in through the console's login URL as an operator does, and drives the pages
with the system chromium (/usr/bin/chromium, headless): the dashboard during a take, the take
list after it, and the guided calibration page on the sim board.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import threading
import uuid
from pathlib import Path

from playwright.sync_api import expect, sync_playwright

from rigd.app.config import RigConfig, default_sim_rig
from rigd.app.console.server import ConsoleServer
from rigd.app.service.daemon import Daemon


def rig(work: Path) -> RigConfig:
    cfg = default_sim_rig(world=f"shots-{uuid.uuid4().hex[:6]}", resolution=(320, 180))
    data = cfg.model_dump(mode="json")
    data["writer"]["disk_reserve_mb"] = 0
    data["service"].update(
        {
            "metrics_port": None,
            "take_dir": str(work / "takes"),
            "control": f"ipc://{work}/control.sock",
            "telemetry": f"ipc://{work}/telemetry.sock",
        }
    )
    return RigConfig.from_data(data)


def shoot(login_url: str, url: str, out: Path) -> None:
    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path="/usr/bin/chromium", headless=True, args=["--no-sandbox"]
        )
        page = browser.new_page(viewport={"width": 1280, "height": 860})
        page.set_default_timeout(120_000)
        page.goto(login_url)  # hands the secret to the tab, lands on the dashboard
        page.get_by_test_id("take-name").fill("walk-1")
        page.get_by_test_id("take-notes").fill("operator walks through the scene")
        page.get_by_test_id("start").click()
        expect(page.get_by_test_id("state")).to_have_text("capturing")
        for dev in ("cam0", "cam1", "cam2", "ev0", "ev1"):
            tile = f"document.querySelector('[data-testid=view-{dev}]')"
            page.wait_for_function(f"Number({tile}.dataset.version) > 15")
        page.screenshot(path=str(out / "console-dashboard.png"))
        page.get_by_test_id("stop").click()
        expect(page.get_by_test_id("state")).to_have_text("idle")
        expect(page.locator('[data-testid="take-row"][data-status="complete"] canvas')).to_have_count(2)
        page.locator("section").last.screenshot(path=str(out / "console-takes.png"))
        page.goto(url + "calibrate")
        page.get_by_test_id("guided-target").fill("2.0")
        page.get_by_test_id("guided-start").click()
        page.wait_for_function("document.querySelectorAll('[data-testid=guided-view]').length >= 6")
        page.wait_for_function("document.querySelector('[data-testid=guided-image]').dataset.version !== '0'")
        page.screenshot(path=str(out / "console-calibrate.png"))
        page.get_by_test_id("guided-finish").click()
        expect(page.get_by_test_id("guided-state")).to_have_text("finished")
        browser.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="rigd-shots-"))
    os.chmod(work, 0o700)
    console = ConsoleServer("127.0.0.1", 0)
    daemon = Daemon(rig(work), attachments=[console])
    th = threading.Thread(target=daemon.serve, name="shots-daemon", daemon=True)
    th.start()
    try:
        if not daemon.wait_ready(60):
            raise SystemExit("daemon did not start")
        shoot(console.login_url, console.url, args.out)
    finally:
        daemon.shutdown()
        th.join(timeout=60)
        shutil.rmtree(work, ignore_errors=True)
    print(f"wrote {', '.join(sorted(p.name for p in args.out.glob('console-*.png')))} to {args.out}")


if __name__ == "__main__":
    main()
