"""
An in-process rclpy listener of a run: what ``rotor-id demo`` prints and the tests assert on.

It subscribes to every output of the five nodes (estimate, progress, state, stirring command,
/diagnostics and, optionally, the sensor topics) with the nodes' own QoS and keeps the messages.
"""

import time

from diagnostic_msgs.msg import DiagnosticArray
import rclpy
from rotor_id.nodes.common import DIAGNOSTICS_QOS, RESULT_QOS, SENSOR_QOS, STATE_QOS
from rotor_id_msgs.msg import (IdentificationProgress, ParameterEstimate, StateEstimate,
                               StirringCommand)
from sensor_msgs.msg import JointState

TOPICS = {
    'estimate': ('/rotor_id/estimate', ParameterEstimate, RESULT_QOS),
    'progress': ('/rotor_id/progress', IdentificationProgress, STATE_QOS),
    # volatile readers: they match a volatile and a transient-local publisher alike
    'state': ('/rotor_id/state', StateEstimate, STATE_QOS),
    'stirring': ('/rotor/stirring', StirringCommand, STATE_QOS),
    'diagnostics': ('/diagnostics', DiagnosticArray, DIAGNOSTICS_QOS),
}
#: The run's outputs of the nodes, one publisher each (not /diagnostics, which every node
#: shares): a display or test waits for these before starting the rotor.
RESULT_KINDS = ('estimate', 'progress', 'state', 'stirring')
SENSOR_TOPICS = {
    'blade_flap': ('/rotor/blade_flap', JointState, SENSOR_QOS),
    'blade_pitch': ('/rotor/blade_pitch', JointState, SENSOR_QOS),
    'azimuth': ('/rotor/azimuth', JointState, SENSOR_QOS),
    'pitch_command': ('/rotor/pitch_command', JointState, SENSOR_QOS),
}


class RunWatcher:
    """Collects the messages of a run; ``on_message(kind, msg)`` is called for each."""

    def __init__(self, node, sensors=False, on_message=None):
        self.node = node
        self.messages = {kind: [] for kind in TOPICS}
        self.on_message = on_message
        self.subscriptions = {}
        topics = dict(TOPICS)
        if sensors:
            topics.update(SENSOR_TOPICS)
            self.messages.update({kind: [] for kind in SENSOR_TOPICS})
        for kind, (topic, cls, qos) in topics.items():
            self.subscriptions[kind] = node.create_subscription(cls, topic, self._callback(kind),
                                                                qos)

    def _callback(self, kind):
        def callback(msg):
            self.messages[kind].append(msg)
            if self.on_message is not None:
                self.on_message(kind, msg)
        return callback

    def final_estimate(self, test_point=None):
        """Return the first test-point result (of ``test_point``, if given), or None yet."""
        for msg in self.messages['estimate']:
            if msg.kind == ParameterEstimate.KIND_FINAL and test_point in (None, msg.test_point):
                return msg
        return None

    def diagnostics(self, name_prefix):
        """Return the statuses on /diagnostics whose name starts with ``name_prefix``."""
        return [status for array in self.messages['diagnostics'] for status in array.status
                if status.name.startswith(name_prefix)]

    def unmatched(self, kinds):
        """Return the kinds among ``kinds`` whose subscription has no matched publisher yet."""
        return [kind for kind in kinds if self.subscriptions[kind].get_publisher_count() == 0]

    def wait_for_publishers(self, kinds, timeout, alive=None):
        """
        Spin until each of ``kinds`` has a matched publisher; return the kinds still without.

        Start a run only after this: a node's publisher that this reader discovers late (DDS
        endpoint discovery on a busy machine can take seconds) delivers only what it still
        keeps, and a plant started at once can finish a short run before that.
        """
        self.spin_until(lambda: not self.unmatched(kinds), timeout, alive)
        return self.unmatched(kinds)

    def spin_until(self, condition, timeout, alive=None):
        """Spin until ``condition()`` is true; False on timeout or when ``alive()`` is false."""
        return _spin_until(self.node, condition, timeout, alive)

    def trigger(self, service, timeout, alive=None):
        """Call a std_srvs/Trigger service until it succeeds (:func:`call_trigger`)."""
        return call_trigger(self.node, service, timeout, alive)


def _spin_until(node, condition, timeout, alive=None):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
        if condition():
            return True
        if alive is not None and not alive():
            return False
    return False


def call_trigger(node, service, timeout, alive=None):
    """
    Call a std_srvs/Trigger service until it succeeds; return its last answer (None: none).

    For ``stirring_input``'s ``~/start``: it refuses while a test point runs and is the only
    way one starts (docs/actuator.md), so a run asks for it explicitly. ``alive()`` false
    stops the attempts.
    """
    from std_srvs.srv import Trigger
    client = node.create_client(Trigger, service)
    deadline = time.monotonic() + timeout
    answer = None
    try:
        while time.monotonic() < deadline and (alive is None or alive()):
            if not client.wait_for_service(timeout_sec=min(1.0, timeout)):
                continue
            future = client.call_async(Trigger.Request())
            if _spin_until(node, future.done, max(0.1, deadline - time.monotonic()), alive):
                answer = future.result()
                if answer.success:
                    return answer
            _spin_until(node, lambda: False, 0.3)
        return answer
    finally:
        node.destroy_client(client)
