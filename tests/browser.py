"""The browser tests' headless Chromium: the package's (:mod:`nerfinv_plugin.viewer.browser`), failing the
test (not skipping it) when the browser is missing, since CI installs it (``.ci/run``)."""

from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from typing import Any

import pytest

from nerfinv_plugin.viewer import browser
from nerfinv_plugin.viewer.browser import BrowserError, element_pixels

__all__ = ["chromium", "element_pixels"]


@contextmanager
def chromium() -> Iterator[Any]:
    """:func:`nerfinv_plugin.viewer.browser.chromium`, with a missing browser a test failure."""
    with ExitStack() as stack:
        try:
            driver = stack.enter_context(browser.chromium())
        except BrowserError as err:
            pytest.fail(str(err))
        yield driver
