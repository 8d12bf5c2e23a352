"""
Shared pieces of the multi-process tests: isolated domains, an rclpy node, bag checks.

Each test runs the installed executables (like ``ros2 run``) in their own processes on a DDS
domain of its own with loopback-only discovery; the test process itself is one more real DDS
participant (no mocks of rclpy).
"""

import math
import os
from pathlib import Path

from cpu_use import CpuUse, starved  # noqa: F401 - the live tests import them here
import pytest
from ros_domains import next_domain

REPO_ROOT = Path(__file__).resolve().parents[2]


def domain_id():
    """Return a ROS_DOMAIN_ID for this test, unique in the run (ros_domains.next_domain)."""
    return next_domain()


def require_workspace():
    """Skip unless the built workspace (install/ and the rotor_id_msgs Python package) is there."""
    if not (REPO_ROOT / 'install' / 'rotor_id' / 'lib' / 'rotor_id' / 'rotor_plant').exists():
        pytest.skip('the workspace is not built (run `make test`, which builds it)')
    try:
        import rclpy  # noqa: F401
        import rotor_id_msgs.msg  # noqa: F401
    except ImportError as exc:
        pytest.skip(f'rclpy or rotor_id_msgs not importable ({exc}); run through `make test`')


class RosClient:
    """rclpy initialised on one domain for the test process, with one node."""

    def __init__(self, domain, name='rotor_id_test'):
        import rclpy
        from rclpy.signals import SignalHandlerOptions
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        os.environ['ROS_DOMAIN_ID'] = str(domain)
        rclpy.init(domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(name)

    def close(self):
        """Destroy the node and shut rclpy down."""
        import rclpy
        self.node.destroy_node()
        rclpy.try_shutdown()


def mcap_messages(bag_dir):
    """
    Decode every message of a bag's MCAP with the independent mcap + mcap-ros2-support.

    Returns {topic: [decoded message, ...]} (custom types decoded from the embedded schemas).
    """
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    files = sorted(Path(bag_dir).glob('*.mcap'))
    assert files, f'no .mcap file in {bag_dir}'
    out = {}
    with open(files[0], 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _schema, channel, _message, decoded in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append(decoded)
    return out


#: family-wise false-alarm rate of one within_sigma check on a correct estimator (Bonferroni):
#: CI makes about twenty such z-checks per run: at a flat 3σ, one run in twenty fails by chance
FAMILY_ALPHA = 1e-3


def within_sigma(values, stds, truth, names, k=None, family=None):
    """
    (ok, text): every |value − truth| ≤ k σ.

    Without ``k`` the bound is Bonferroni's for ``family`` z-values (default: this estimate's
    parameters) at a family-wise rate FAMILY_ALPHA: 3.59σ for three parameters, 3.87σ for nine.
    """
    if k is None:
        from scipy.special import ndtri
        k = float(ndtri(1.0 - FAMILY_ALPHA / (2 * (family or len(names)))))
    z = [(v - truth[n]) / s for n, v, s in zip(names, values, stds)]
    text = ', '.join(f'{n} = {v:.4f} ± {s:.4f} (true {truth[n]}, z = {zz:+.2f})'
                     for n, v, s, zz in zip(names, values, stds, z))
    return all(math.isfinite(zz) and abs(zz) <= k for zz in z), text
