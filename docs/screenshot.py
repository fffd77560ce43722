"""Regenerate the README's picture of the report: `make screenshot`.

    python docs/screenshot.py [RUN_DIR] [--out docs/report-quick.png]

Opens RUN_DIR/report/index.html (written by `mcillum validate --out RUN_DIR`;
`make screenshot` runs the quick profile first) in headless Chromium, takes the
top of the page, and writes it as PNG with the code that drew it: a hash of
validation/report/*.py and *.js in its text chunk ``mcillum-report``. The test
``tests/test_docs.py`` compares that hash with the code as it stands, so a change
to the report fails the tests until the picture is taken again.
Needs Debian's chromium and chromium-driver (``make browser``).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import os
import shutil
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REPORT_CODE = os.path.join(ROOT, "validation", "report")
KEY = "mcillum-report"


def report_code_hash() -> str:
    """sha256 of the report's code (validation/report/*.py and *.js, by name)."""
    h = hashlib.sha256()
    for name in sorted(os.listdir(REPORT_CODE)):
        if name.endswith((".py", ".js")):
            h.update(name.encode())
            with open(os.path.join(REPORT_CODE, name), "rb") as f:
                h.update(f.read())
    return h.hexdigest()


def screenshot(page: str, out: str, width: int = 1200, height: int = 1100) -> float:
    """Write the top ``width``×``height`` of ``page`` to ``out`` (PNG,
    tagged with :func:`report_code_hash`); return the seconds from the start
    of navigation until every viewer had decoded its data (the page's opening
    time, as a reader waits for it). Raises RuntimeError without Chromium."""
    from PIL import Image, PngImagePlugin
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.support.ui import WebDriverWait

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver_path = shutil.which("chromedriver")
    if not (chromium and driver_path):
        raise RuntimeError("needs Debian's chromium and chromium-driver: run `make browser`")
    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    with tempfile.TemporaryDirectory() as profile:
        for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
                     "--hide-scrollbars", "--force-device-scale-factor=1",
                     f"--window-size={width},{height}", f"--user-data-dir={profile}"):
            opts.add_argument(flag)
        driver = webdriver.Chrome(service=Service(driver_path), options=opts)
        try:
            driver.get("file://" + os.path.abspath(page))
            WebDriverWait(driver, 30).until(lambda d: d.execute_script(
                "return document.documentElement.dataset.viewersReady"))
            opened = float(driver.execute_script(
                "return document.documentElement.dataset.viewersReady")) / 1e3
            png = driver.get_screenshot_as_png()
        finally:
            driver.quit()
    info = PngImagePlugin.PngInfo()
    info.add_text(KEY, report_code_hash())
    Image.open(io.BytesIO(png)).convert("RGB").save(out, pnginfo=info, optimize=True)
    return opened


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", nargs="?", default="out/validate")
    p.add_argument("--out", default=os.path.join(ROOT, "docs", "report-quick.png"))
    args = p.parse_args(argv)
    page = os.path.join(args.run_dir, "report", "index.html")
    if not os.path.isfile(page):
        print(f"{page} is missing: run `mcillum validate --out {args.run_dir}` first",
              file=sys.stderr)
        return 2
    opened = screenshot(page, args.out)
    print(f"wrote {args.out}; the page ({os.path.getsize(page) / 1e6:.2f} MB) opened in "
          f"{opened:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
