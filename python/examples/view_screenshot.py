"""Screenshot of `twinstack view` in headless Chromium, for the book.

Starts `twinstack view` on PORT (default: the simulated board in-process) with the given tune
and calibration figures, opens it in headless Chromium (selenium), switches to closed loop
and starts the waveform from the page, waits, and saves a PNG of the page.

    TWINSTACK_HAL_SIM=target/debug/twinstack python python/examples/view_screenshot.py \\
        --tune tune.json --calibration cal.json --out docs/src/guide/view.png
"""

import argparse
import os
import shutil
import subprocess
import tempfile
import time

from selenium import webdriver
from selenium.webdriver.chrome.options import Options
from selenium.webdriver.chrome.service import Service


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--port", default="sim")
    ap.add_argument("--tune")
    ap.add_argument("--calibration")
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--out", default="view.png")
    args = ap.parse_args()
    hal_sim = os.environ.get("TWINSTACK_HAL_SIM", "twinstack")
    cmd = [hal_sim, "view", "--port", args.port, "--listen", "127.0.0.1:0"]
    if args.tune:
        cmd += ["--tune", args.tune]
    if args.calibration:
        cmd += ["--calibration", args.calibration]
    view = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    profile = tempfile.mkdtemp(prefix="twinstack-chromium-")
    try:
        line = view.stdout.readline()
        url = next(w for w in line.split() if w.startswith("http://"))
        options = Options()
        options.binary_location = shutil.which("chromium") or "chromium"
        for flag in (
            "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--no-first-run",
            "--window-size=1400,1150", f"--user-data-dir={profile}",
        ):
            options.add_argument(flag)
        driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
        try:
            driver.get(url)
            time.sleep(1.0)
            driver.find_element("id", "mode-closed-loop").click()
            driver.find_element("id", "wf-start").click()
            time.sleep(args.seconds)
            driver.save_screenshot(args.out)
            v = driver.execute_script("return window.twinstackView;")
            print(f"wrote {args.out}: {v['samples']} samples on the page, board's count {v['counts']}")
        finally:
            driver.quit()
    finally:
        view.kill()
        view.wait()
        shutil.rmtree(profile, ignore_errors=True)


if __name__ == "__main__":
    main()
