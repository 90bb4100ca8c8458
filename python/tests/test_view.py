"""`twinstack view` in a real headless browser (Debian's Chromium and its driver, via selenium):
the page loads, its plot receives telemetry, the page's own count of samples equals the
board's count once telemetry is paused (nothing lost between the board and the page), and a
mode switch clicked on the page reaches the board.

The run length is `TWINSTACK_VIEW_SECONDS` (default 60 s).
"""

import os
import shutil
import subprocess
import tempfile
import time

import pytest

import twinstack

webdriver = pytest.importorskip("selenium.webdriver")

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
SECONDS = float(os.environ.get("TWINSTACK_VIEW_SECONDS", "60"))

pytestmark = pytest.mark.skipif(
    not (CHROMIUM and CHROMEDRIVER),
    reason="chromium and chromedriver are not installed (cargo xtask setup installs them)",
)


def start_view(hal_sim, port, *extra):
    proc = subprocess.Popen(
        [hal_sim, "view", "--port", port, "--listen", "127.0.0.1:0", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    line = proc.stdout.readline()
    # "view of PORT on http://127.0.0.1:NNNN/ (...)"
    if proc.poll() is not None or "http://" not in line:
        proc.kill()
        raise RuntimeError(f"view did not start: {line!r} {proc.stderr.read()!r}")
    url = next(w for w in line.split() if w.startswith("http://"))
    return proc, url


@pytest.fixture
def browser():
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="twinstack-chromium-")
    options = Options()
    options.binary_location = CHROMIUM
    for flag in (
        "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run",
        "--window-size=1400,1000", f"--user-data-dir={profile}",
    ):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    yield driver
    driver.quit()
    shutil.rmtree(profile, ignore_errors=True)


def page(driver, expr):
    return driver.execute_script(f"return {expr};")


def wait_for(what, check, timeout=30.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = check()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def test_the_view_plots_every_sample_and_switches_the_mode(hal_sim, virtual_board, browser):
    board = twinstack.Board(virtual_board)
    board.stop()
    board.recall()
    board.mode("bypass")
    board.close()  # the view takes the board's one link
    # 2 000 samples a second of each signal on the board's clock: the page keeps up with at
    # least 1 000 a second of wall time even where the virtual board runs at half speed.
    proc, url = start_view(hal_sim, virtual_board, "--signals", "setpoint,sensor", "--rate", "2000")
    try:
        browser.get(url)
        assert "twinstack view" in browser.title
        wait_for("samples on the page", lambda: page(browser, "window.twinstackView.samples") > 0)
        assert page(browser, "window.twinstackView.signals") == ["setpoint", "sensor"]
        assert page(browser, "window.twinstackView.rateHz") == 2000.0

        # A waveform started from the page: the sensor moves in the plot's buffer.
        browser.find_element("id", "wf-start").click()
        wait_for("the waveform", lambda: "waveform" in (page(browser, "window.twinstackView.status") or {}).get("flags", []))

        # The mode switch, clicked: the board's status says closed loop.
        browser.find_element("id", "mode-closed-loop").click()
        wait_for(
            "closed loop on the board",
            lambda: (page(browser, "window.twinstackView.status") or {}).get("mode") == "closed-loop",
        )
        # What the page shows (the status table is redrawn every 250 ms: read it in one go).
        assert page(browser, "document.getElementById('status-mode').textContent") == "closed-loop"

        t0 = time.monotonic()
        s0 = page(browser, "window.twinstackView.samples")
        time.sleep(SECONDS)
        wall = time.monotonic() - t0
        received = page(browser, "window.twinstackView.samples") - s0
        draws = page(browser, "window.twinstackView.draws")

        # Pause telemetry: the board's end frame gives the count it produced.
        browser.find_element("id", "tel-pause").click()
        counts = wait_for(
            "the end of telemetry",
            lambda: (page(browser, "window.twinstackView.counts") or {}).get("produced"),
        )
        produced = counts
        wait_for(
            "the last samples",
            lambda: page(browser, "window.twinstackView.samples + window.twinstackView.start") >= produced,
            timeout=10,
        )
        view = page(browser, "window.twinstackView")
        assert view["samples"] == produced - view["start"], (view["samples"], view["start"], produced)
        assert view["counts"]["missing"] == 0 and view["counts"]["lost_on_board"] == 0
        assert view["gaps"] == 0 and view["missedMessages"] == 0
        assert draws > SECONDS, "the plot was redrawn"
        print(
            f"\nview: {received} samples of 2 signals in {wall:.1f} s on the page "
            f"({received / wall:.0f} samples/s per signal, board time at 2000/s), "
            f"{produced} produced, {view['samples']} on the page, {draws} redraws"
        )

        # The board itself (its link back to the view's owner once the view has gone).
    finally:
        proc.kill()
        proc.wait()
    board = twinstack.Board(virtual_board)
    try:
        assert board.status()["mode"] == "closed-loop"
        board.stop()
        board.mode("bypass")
    finally:
        board.close()


def test_a_refused_command_shows_its_reason_on_the_page(hal_sim, browser):
    proc, url = start_view(hal_sim, "sim", "--signals", "sensor", "--rate", "500")
    try:
        browser.get(url)
        wait_for("samples", lambda: page(browser, "window.twinstackView.samples") > 0)
        amp = browser.find_element("id", "wf-amplitude")
        amp.clear()
        amp.send_keys("1.5")
        browser.find_element("id", "wf-start").click()
        msg = wait_for("the refusal", lambda: browser.find_element("id", "message").text)
        assert "amplitude" in msg.lower(), msg
        assert "error" in browser.find_element("id", "message").get_attribute("class")
    finally:
        proc.kill()
        proc.wait()
