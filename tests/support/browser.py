"""Headless Chromium for the page tests: Debian's ``chromium`` and ``chromium-driver`` driven by
Selenium, nothing downloaded. :func:`browser_problem` says why a browser cannot run here (the
tests skip with that reason); :func:`chromium` starts one.

    with chromium() as driver:
        driver.get(url)
        console_errors(driver)        # the console's SEVERE entries since the last call
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator

__all__ = ["browser_problem", "chromium", "console_errors", "CHROMIUM_FLAGS", "find_binary"]

CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--no-first-run", "--disable-sync", "--disable-dev-shm-usage",
                  "--hide-scrollbars", "--force-device-scale-factor=1")
"""Headless, no sandbox (containers run as root), nothing fetched in the background."""


def find_binary(*names: str) -> str | None:
    """The first of ``names`` on PATH or in /usr/bin, None if none is installed."""
    for name in names:
        path = shutil.which(name) or (f"/usr/bin/{name}" if os.access(f"/usr/bin/{name}", os.X_OK) else None)
        if path:
            return path
    return None


def browser_problem() -> str | None:
    """None if Selenium and the system Chromium with its driver are installed, else what is missing."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "browser tests need selenium: pip install -e '.[test]'"
    if find_binary("chromium", "chromium-browser") is None:
        return "browser tests need Debian's chromium: apt-get install -y chromium chromium-driver (.ci/run does)"
    if find_binary("chromedriver") is None:
        return "browser tests need chromium-driver: apt-get install -y chromium-driver (.ci/run does)"
    return None


@contextlib.contextmanager
def chromium(width: int = 1280, height: int = 900) -> Iterator:
    """A headless Chromium WebDriver with the browser's console log kept (``console_errors``)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = find_binary("chromium", "chromium-browser")
    for flag in CHROMIUM_FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--window-size={width},{height}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(executable_path=find_binary("chromedriver")), options=options)
    try:
        yield driver
    finally:
        driver.quit()


def console_errors(driver) -> list[str]:
    """The browser console's errors (level SEVERE) logged since the last call."""
    return [e["message"] for e in driver.get_log("browser") if e.get("level") == "SEVERE"]
