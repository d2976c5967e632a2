"""Render the README picture (docs/img/views.png) from the current code: the default job's
overview tab in the Rerun web viewer, screenshot by headless Chromium.

Runs ``bttsim run --out DIR`` (the default scenario; ``--from DIR`` reuses a run already
there), serves ``DIR/run.mcap`` through :func:`bttsim_stream.views.log_recording` on
loopback ports, opens the page in Debian's Chromium with Playwright (software rendering:
only loopback requests are let through) and screenshots the page every 15 s until two
screenshots in a row are identical, then copies the last one to ``--out``. The resonance
table in the picture is the recording's own resonance report, the one ``DIR/summary.json``
holds: the script prints that summary's E_A and E_f to compare with the picture.

Needs the ``test`` extra (Playwright) and ``chromium`` (``apt-get install chromium``).
Usage: ``python scripts/make_readme_picture.py [--from DIR] [--out docs/img/views.png]``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from urllib.parse import urlparse

REPO = Path(__file__).resolve().parents[1]
VIEWPORT = {"width": 1600, "height": 1000}
_CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def _loopback_only(route) -> None:
    url = route.request.url
    if urlparse(url).hostname in ("127.0.0.1", "localhost") or url.startswith(("data:", "blob:")):
        route.continue_()
    else:
        route.abort()  # the page links web fonts: never wait for the network


def screenshot(url: str, out: Path, *, chromium: str, budget_s: float = 900.0, first_wait_s: float = 45.0,
               every_s: float = 15.0) -> int:
    """Screenshot ``url`` to ``out`` once two screenshots ``every_s`` apart are identical;
    returns the number taken. Raises ``TimeoutError`` past ``budget_s``."""
    from playwright.sync_api import sync_playwright

    deadline = time.monotonic() + budget_s
    with tempfile.TemporaryDirectory() as profile, sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(profile, executable_path=chromium, args=_CHROMIUM_ARGS,
                                                   headless=True, viewport=VIEWPORT)
        try:
            page = ctx.new_page()
            page.route("**/*", _loopback_only)
            page.goto(url, wait_until="domcontentloaded", timeout=120_000)
            page.wait_for_timeout(first_wait_s * 1000)
            last, n = None, 0
            while True:
                shot = page.screenshot(timeout=180_000)
                n += 1
                if shot == last:
                    out.write_bytes(shot)
                    return n
                if time.monotonic() > deadline:
                    raise TimeoutError(f"the page did not settle in {budget_s:.0f} s ({n} screenshots)")
                last = shot
                page.wait_for_timeout(every_s * 1000)
        finally:
            ctx.close()


def main(run_dir: Path, out: Path, *, rerun_job: bool, chromium: str) -> None:
    from bttsim_stream import views
    from bttsim_stream.bus.session import free_port

    t0 = time.monotonic()
    if rerun_job:
        subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "run", "--out", str(run_dir)], check=True,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})
    summary = json.loads((run_dir / "summary.json").read_text())
    print(f"summary.json: E_A mean {summary['mean_E_A_pct']:.3f} %, max {summary['max_E_A_pct']:.3f} %; "
          f"E_f mean {summary['mean_E_f_pct']:.4f} %, max {summary['max_E_f_pct']:.4f} %", flush=True)
    t1 = time.monotonic()
    session = views.log_recording(run_dir / "run.mcap", None, serve_web=True, web_port=free_port(),
                                  grpc_port=free_port())
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        n = screenshot(session.sinks.web_url, out, chromium=chromium)
    finally:
        session.close()
    t2 = time.monotonic()
    print(f"{out}: {n} screenshots; job {t1 - t0:.0f} s, views and screenshot {t2 - t1:.0f} s", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--from", dest="run_dir", type=Path,
                        help="a directory holding run.mcap and summary.json of the default job (default: run it)")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "img" / "views.png")
    args = parser.parse_args()
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        sys.exit("error: chromium not found (apt-get install chromium)")
    with tempfile.TemporaryDirectory() as tmp:
        main(args.run_dir or Path(tmp) / "out", args.out, rerun_job=args.run_dir is None, chromium=browser)
