"""A real headless Chromium: Debian's ``chromium`` driven by ``chromium-driver`` through Selenium, with WebGL
drawn in software (SwiftShader), so a WebGL canvas such as viser's really draws on a machine without a GPU.
The browser tests watch the viewer and open the report with it, and ``ns-invert-bench viewer`` measures what
one watching browser costs a run. Selenium comes with the test extra (``pip install 'nerfinv[test]'``) and is
imported only when a browser is started, so the package itself does not need it."""

import io
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
from PIL import Image

CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-gl=angle",
                  "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--window-size=1024,768")
"""SwiftShader through ANGLE; Chromium 150 (Debian 12) draws WebGL with either the two --use flags or
--enable-unsafe-swiftshader alone, newer ones only with the latter, so both are given."""


class BrowserError(Exception):
    """No headless Chromium can be started here, or it did not do what it was asked; the message says how
    to fix it."""


def find_chromium() -> tuple[str, str]:
    """The paths of chromium and chromedriver; raises :class:`BrowserError` when selenium or either of them
    is missing, so that a command can say so before it starts long work."""
    try:
        import selenium  # noqa: F401  (only whether it is installed)
    except ImportError:
        raise BrowserError("selenium is needed to drive chromium: pip install 'nerfinv[test]'") from None
    binary, driver_path = shutil.which("chromium"), shutil.which("chromedriver")
    if binary is None or driver_path is None:
        raise BrowserError("chromium and chromium-driver are needed: apt-get install -y chromium chromium-driver")
    return binary, driver_path


@contextmanager
def chromium() -> Iterator[Any]:
    """A Selenium driver (``selenium.webdriver.Chrome``) of headless Chromium, quit on leaving. Raises
    :class:`BrowserError` when selenium, chromium or chromedriver is missing."""
    binary, driver_path = find_chromium()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for flag in CHROMIUM_FLAGS:
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=Service(driver_path))
    try:
        yield driver
    finally:
        driver.quit()


def element_pixels(element: Any) -> np.ndarray:
    """[H, W, 3] uint8 screenshot of one element (a Selenium ``WebElement``, not the page)."""
    return np.asarray(Image.open(io.BytesIO(element.screenshot_as_png)).convert("RGB"))
