"""A real headless Chromium for the browser tests: Debian's ``chromium`` driven by ``chromium-driver``
through Selenium, with WebGL drawn in software (SwiftShader), so a WebGL canvas really draws on a machine
without a GPU. ``.ci/run`` installs both packages."""

import io
import shutil
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest
from PIL import Image

CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-gl=angle",
                  "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--window-size=1024,768")
"""SwiftShader through ANGLE; Chromium 150 (Debian 12) draws WebGL with either the two --use flags or
--enable-unsafe-swiftshader alone, newer ones only with the latter, so both are given."""


@contextmanager
def chromium() -> Iterator:
    """A Selenium driver of headless Chromium; fails (not skips) when the browser is missing, since CI
    installs it."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    binary, driver_path = shutil.which("chromium"), shutil.which("chromedriver")
    if binary is None or driver_path is None:
        pytest.fail("chromium and chromium-driver are needed: apt-get install -y chromium chromium-driver")
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for flag in CHROMIUM_FLAGS:
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=Service(driver_path))
    try:
        yield driver
    finally:
        driver.quit()


def element_pixels(element) -> np.ndarray:
    """[H, W, 3] uint8 screenshot of one element (not the page)."""
    return np.asarray(Image.open(io.BytesIO(element.screenshot_as_png)).convert("RGB"))
