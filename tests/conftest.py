"""Shared pytest configuration: the test tiers.

* ``unit`` -- in-process (at most a short Python subprocess), no network: the default of every
  test that declares no tier;
* ``integration`` -- real node processes, Zenoh sessions on loopback, ``bttsim run``;
* ``browser`` -- the Rerun web viewer in headless Chromium (slow: software rendering).

``python -m pytest`` runs them all; ``-m unit`` (about a minute) or ``-m "not browser"`` select.
"""

import pytest

TIERS = ("unit", "integration", "browser")


def pytest_configure(config):
    config.addinivalue_line("markers", "unit: in-process tests of one module (the default tier)")
    config.addinivalue_line("markers", "integration: real processes, Zenoh sessions on loopback, files")
    config.addinivalue_line(
        "markers", "browser: needs headless Chromium and Playwright (slow: the Rerun web viewer renders in software)")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if not any(item.get_closest_marker(t) for t in TIERS):
            item.add_marker(pytest.mark.unit)
