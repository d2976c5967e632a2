"""Shared pytest configuration."""


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "browser: needs headless Chromium and Playwright (slow: the Rerun web viewer renders in software)")
    config.addinivalue_line("markers", "unit: pure functions, in memory, fast")
    config.addinivalue_line("markers", "integration: real files, processes or nodes on loopback")
