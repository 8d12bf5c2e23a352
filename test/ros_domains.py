"""
ROS_DOMAIN_IDs for the tests: unique within a test run, also across pytest-xdist workers.

Every test that starts rclpy or ROS processes takes its domain from :func:`next_domain`, so two
tests that run at the same time (one per xdist worker) never share a DDS domain and never see
each other's topics. Worker k of n takes the ids k+1, k+1+n, k+1+2n, ... in turn; a worker runs
its tests one after the other, so reusing an id after a full cycle is safe. Ids stay within
1..DOMAIN_MAX: Fast DDS's default port mapping (7400 + 250·id + offsets) must stay below the
65535 port limit, which allows ids up to 232.
"""

import itertools
import os

DOMAIN_MAX = 232
_counter = itertools.count()


def _worker():
    """Return (index, count) of this pytest-xdist worker; (0, 1) without xdist."""
    name = os.environ.get('PYTEST_XDIST_WORKER', 'gw0')
    count = int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1'))
    return int(name.removeprefix('gw') or 0), max(count, 1)


def next_domain() -> int:
    """Return a ROS_DOMAIN_ID that no other test of this run uses at the same time."""
    index, count = _worker()
    per_worker = DOMAIN_MAX // count
    return 1 + index + count * (next(_counter) % per_worker)
