"""pytest plugin for runs inside the qemu guest: keep only the tests that use the bus.

Loaded with ``-p pytest_bus_only`` (tests/vm on PYTHONPATH) by
tests/test_vm_canopen_conformance.py. Python runs 20-40x slower under TCG, so the guest runs
only the tests that request the ``drive_sim`` fixture (directly or through ``co_node``):
those exercise the SocketCAN transport. The rest (EDS generation, docs tables, bad input)
does not depend on the transport and already runs on the host. The deselected tests are
reported in pytest's summary line ("N deselected").
"""

BUS_FIXTURE = "drive_sim"


def pytest_collection_modifyitems(config, items):
    keep, drop = [], []
    for item in items:
        (keep if BUS_FIXTURE in getattr(item, "fixturenames", ()) else drop).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep
