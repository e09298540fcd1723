"""The live map's picture in the docs (``docs/img/live-map.png``), taken from a real run.

Runs ``slcp run SCENARIO --view``, opens the page in headless Chromium (Debian's ``chromium``
package, driven by Playwright: ``pip install '.[dev]'``), waits until the run's sensor time
reaches ``--at`` seconds, zooms in ``--zoom`` wheel steps on the map's centre and saves the page::

    python tools/live_map_screenshot.py docs/img/live-map.png
"""

from __future__ import annotations

import argparse
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("png", type=Path)
    ap.add_argument("--scenario", default="paper-1")
    ap.add_argument("--at", type=float, default=34.0, help="sensor time of the picture [s] (default 34)")
    ap.add_argument("--zoom", type=int, default=4, help="wheel steps in (default 4)")
    ap.add_argument("--speed", type=float, default=1.0, help="real-time factor of the run (default 1)")
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    exe = shutil.which("chromium")
    if exe is None:
        raise SystemExit("needs Debian's chromium: apt-get install chromium")
    port = _free_port()
    with tempfile.TemporaryDirectory() as tmp:
        run = subprocess.Popen([sys.executable, "-m", "slcp.deploy.cli", "run", args.scenario, "--out",
                                str(Path(tmp) / "run"), "--speed", str(args.speed), "--view", str(port)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=exe, args=[
                    "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                    "--disable-component-update", "--disable-sync", "--no-first-run"])
                page = browser.new_page(viewport={"width": 1280, "height": 720})
                deadline = time.monotonic() + 120
                while True:
                    try:
                        page.goto(f"http://127.0.0.1:{port}/")
                        break
                    except Exception:  # noqa: BLE001 - the server is not up yet
                        if time.monotonic() > deadline or run.poll() is not None:
                            raise
                        time.sleep(0.5)
                page.wait_for_function("at => { const r = document.querySelector('tr.vehicle');"
                                       " return r !== null && +r.dataset.t >= at; }", arg=args.at, timeout=120_000)
                box = page.locator("#map").bounding_box()
                page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
                for _ in range(args.zoom):
                    page.mouse.wheel(0, -300)
                page.wait_for_timeout(300)
                page.screenshot(path=str(args.png))
                browser.close()
        finally:
            run.terminate()
            run.wait(60)
    print(args.png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
