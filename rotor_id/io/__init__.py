# noqa: A005 (the package layout names this subpackage io; it is imported as rotor_id.io)
"""
Input layer: rosbag2 recordings, run descriptions and the time base (no rclpy).

``from rotor_id.io import read_run, load_run_description`` reads a run and its recording::

    desc = load_run_description('recordings/id_wake_progressing.yaml')
    record = read_run(desc)                 # bag NAME/ beside NAME.yaml, window checked
    window = record.window(*desc.window_s)  # samples used for identification
"""

from importlib import import_module
from typing import Any, TYPE_CHECKING

if TYPE_CHECKING:
    from rotor_id.io.bag import (
        BagWriter, open_writer, read_record, read_run, register_msg_dir, write_record_bag,
    )
    from rotor_id.io.errors import (
        BagError, BagWarning, RunDescriptionError, RunDescriptionWarning,
    )
    from rotor_id.io.record import Record
    from rotor_id.io.run_description import (
        load_run_description, MODEL_PARAMETERS, MODELS, parse_run_description, RunDescription,
        validate_window,
    )
    from rotor_id.io.timebase import blade_azimuths, blade_values, multiblade_coordinates

#: Where each public name is defined. Loaded on first use: a node that needs only the run
#: description or the time base does not load the bag reader (rosbags, about 0.07 s).
_DEFINED_IN = {
    **dict.fromkeys(('BagWriter', 'open_writer', 'read_record', 'read_run',
                     'register_msg_dir', 'write_record_bag'), 'bag'),
    **dict.fromkeys(('BagError', 'BagWarning', 'RunDescriptionError',
                     'RunDescriptionWarning'), 'errors'),
    'Record': 'record',
    **dict.fromkeys(('load_run_description', 'MODEL_PARAMETERS', 'MODELS',
                     'parse_run_description', 'RunDescription', 'validate_window'),
                    'run_description'),
    **dict.fromkeys(('blade_azimuths', 'blade_values', 'multiblade_coordinates'), 'timebase'),
}

__all__ = [
    'BagError', 'BagWarning', 'BagWriter', 'MODELS', 'MODEL_PARAMETERS', 'Record',
    'RunDescription', 'RunDescriptionError', 'RunDescriptionWarning', 'blade_azimuths',
    'blade_values', 'load_run_description', 'multiblade_coordinates', 'open_writer',
    'parse_run_description', 'read_record', 'read_run', 'register_msg_dir', 'validate_window',
    'write_record_bag',
]


def __getattr__(name: str) -> Any:
    """Return a public name of the input layer, loading its module on first use (PEP 562)."""
    if name not in _DEFINED_IN:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    return getattr(import_module(f'{__name__}.{_DEFINED_IN[name]}'), name)
