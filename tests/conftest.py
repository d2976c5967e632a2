"""Shared pytest configuration."""


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "browser: needs headless Chromium and Playwright (slow: the Rerun web viewer renders in software)")
    config.addinivalue_line("markers", "unit: fast, in-process tests of one module")
    config.addinivalue_line("markers", "integration: real processes, Zenoh sessions, files (slower)")
