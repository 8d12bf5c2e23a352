"""The five rclpy nodes of rotor_id (one per module) and their ROS-free helpers (live.py)."""
