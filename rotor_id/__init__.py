"""rotor_id: identification of rotor blade flapping dynamics (ROS 2 Jazzy, Python)."""
