# noqa: A005 (the package layout names this subpackage io; it is imported as rotor_id.io)
"""
Input layer: rosbag2 recordings, run descriptions and the time base (no rclpy).

``from rotor_id.io import read_run, load_run_description`` reads a run and its recording::

    desc = load_run_description('recordings/id_wake_progressing.yaml')
    record = read_run(desc)                 # bag NAME/ beside NAME.yaml, window checked
    window = record.window(*desc.window_s)  # samples used for identification
"""

from rotor_id.io.bag import (
    BagWriter, open_writer, read_record, read_run, register_msg_dir, write_record_bag,
)
from rotor_id.io.errors import BagError, BagWarning, RunDescriptionError, RunDescriptionWarning
from rotor_id.io.record import Record
from rotor_id.io.run_description import (
    load_run_description, MODEL_PARAMETERS, MODELS, parse_run_description, RunDescription,
    validate_window,
)
from rotor_id.io.timebase import blade_azimuths, blade_values, multiblade_coordinates

__all__ = [
    'BagError', 'BagWarning', 'BagWriter', 'MODELS', 'MODEL_PARAMETERS', 'Record',
    'RunDescription', 'RunDescriptionError', 'RunDescriptionWarning', 'blade_azimuths',
    'blade_values', 'load_run_description', 'multiblade_coordinates', 'open_writer',
    'parse_run_description', 'read_record', 'read_run', 'register_msg_dir', 'validate_window',
    'write_record_bag',
]
