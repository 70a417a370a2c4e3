"""Headless Chromium for the browser tests: the package's driver (:mod:`ar_anchor.viz.browser`)."""

from ar_anchor.viz.browser import Browser, BrowserError, find_chromium

__all__ = ["Browser", "BrowserError", "find_chromium"]
