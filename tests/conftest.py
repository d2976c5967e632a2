"""Shared pytest configuration."""


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "browser: needs headless Chromium and Playwright (slow: the Rerun web viewer renders in software)")
