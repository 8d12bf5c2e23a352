"""
One identifier node in the test's process, fed through DDS by a test node (no mocks of rclpy).

Shared by the in-process identifier tests: the node and a test node on a context and domain of
their own, one executor spinning both, publishers of the three sensor topics, the estimates
collected, and the sensor topics taken by the test (``drain``), not by the node's poller
thread, so that a starved identifier is one whose poll does not run.
"""

import os

SENSORS = ('blade_flap', 'blade_pitch', 'azimuth')


class InProcessIdentifier:
    """
    The identifier with ``params`` (rclpy Parameters), its test node and executor.

    The test node publishes the sensors with ``sensor_qos`` (default: reliable, as rotor_plant
    offers them).
    """

    def __init__(self, name, params, domain, sensor_qos=None):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        from rotor_id.nodes.common import RESULT_QOS, SENSOR_OFFER_QOS
        from rotor_id.nodes.identifier import Identifier
        from rotor_id_msgs.msg import ParameterEstimate
        from sensor_msgs.msg import JointState

        self.rclpy = rclpy
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context, domain_id=domain,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = Identifier(parameter_overrides=params, context=self.context)
        self.node.poller.stop()
        self.test = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.test)
        self.pubs = {topic: self.test.create_publisher(JointState, f'/rotor/{topic}',
                                                       sensor_qos or SENSOR_OFFER_QOS)
                     for topic in SENSORS}
        self.estimates = []
        self.test.create_subscription(ParameterEstimate, '/rotor_id/estimate',
                                      self.estimates.append, RESULT_QOS)

    def spin_until(self, condition, timeout=30.0):
        """Spin until ``condition()``; return whether it came within ``timeout`` s."""
        clock = self.rclpy.clock.Clock(clock_type=self.rclpy.clock.ClockType.STEADY_TIME)
        end = clock.now().nanoseconds + timeout * 1e9
        while not condition():
            if clock.now().nanoseconds > end:
                return False
            self.executor.spin_once(timeout_sec=0.01)
        return True

    def drain(self):
        """Spin until the identifier has taken everything delivered (no callback for 3 spins)."""
        idle = 0
        while idle < 3:
            before = self.node.taken
            self.node.poller.poll()
            self.executor.spin_once(timeout_sec=0.002)
            idle = idle + 1 if self.node.taken == before else 0

    def send(self, data, i, omega, blades, topics=SENSORS):
        """Publish sample ``i`` of a simulated stream on ``topics``."""
        from rotor_id.nodes.common import joint_state
        stamp = int(data['stamps'][i])
        for topic in topics:
            if topic == 'azimuth':
                msg = joint_state(stamp, ['rotor'], [data['psi'][i]], [omega])
            else:
                msg = joint_state(stamp, blades, data['flap' if topic == 'blade_flap'
                                                      else 'pitch'][i])
            self.pubs[topic].publish(msg)

    def final_of(self, number):
        """Say whether test point ``number``'s final estimate has arrived."""
        return any(m.test_point == number and m.kind == 1 for m in self.estimates)

    def close(self):
        """Stop the node and shut its context down."""
        self.node.close()
        self.executor.shutdown()
        self.node.destroy_node()
        self.test.destroy_node()
        self.rclpy.try_shutdown(context=self.context)
