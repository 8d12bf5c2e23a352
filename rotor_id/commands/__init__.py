"""One module per ``rotor-id`` command (see rotor_id.cli)."""
