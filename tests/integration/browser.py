"""Headless Chromium (Debian's chromium and chromium-driver) driven through Selenium.

Both come from the same Debian package source, so the driver always matches
the browser; Selenium is pointed at them and never downloads anything.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile

from selenium import webdriver
from selenium.webdriver.chrome.service import Service


def _path(*names):
    for n in names:
        found = shutil.which(n) or (n if os.path.isabs(n) and os.path.exists(n) else None)
        if found:
            return found
    raise RuntimeError(f"none of {names} is installed; tools/bootstrap installs Debian's chromium and chromium-driver")


@contextlib.contextmanager
def chromium(width=1400, height=1000, trust_ca=None):
    """trust_ca: a CA certificate (PEM path) the browser trusts for servers, as a person who
    imported it would: it goes into an NSS database of the browser's own (a home of its own)."""
    env = None
    home = tempfile.TemporaryDirectory(prefix="chromium-home-") if trust_ca else None
    if trust_ca:
        nssdb = os.path.join(home.name, ".pki", "nssdb")
        os.makedirs(nssdb)
        for argv in (
            ["certutil", "-N", "-d", f"sql:{nssdb}", "--empty-password"],
            ["certutil", "-A", "-d", f"sql:{nssdb}", "-n", "isaacsim.fleet CA", "-t", "C,,", "-i", str(trust_ca)],
        ):
            subprocess.run([_path(argv[0]), *argv[1:]], check=True, capture_output=True)
        env = dict(os.environ, HOME=home.name)
    options = webdriver.ChromeOptions()
    options.binary_location = _path("chromium", "/usr/lib/chromium/chromium")
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={width},{height}"):
        options.add_argument(arg)
    # every console message and failed load, from the page and its frames
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    service = Service(_path("chromedriver", "/usr/lib/chromium/chromedriver"), env=env)
    driver = webdriver.Chrome(service=service, options=options)
    try:
        yield driver
    finally:
        driver.quit()
        if home:
            home.cleanup()


def console_errors(driver) -> list:
    return [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]
