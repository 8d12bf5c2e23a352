"""The ``rotor-id`` command line (placeholder: the commands are being written).

Run it from a clone with ``./rotor-id <command>`` (no sourcing needed) or, in a sourced
workspace, as ``ros2 run rotor_id rotor-id <command>``.
"""

import argparse
import sys

COMMANDS = {
    'demo': 'identify the built-in simulated rotor end to end',
}


def build_parser():
    """Return the argument parser with one subcommand per entry of COMMANDS."""
    parser = argparse.ArgumentParser(
        prog='rotor-id', description='Identify rotor flapping dynamics.')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    for name, help_text in COMMANDS.items():
        sub.add_parser(name, help=help_text)
    return parser


def main(argv=None):
    """Parse ``argv`` and run the chosen command; return the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    print(f'rotor-id {args.command}: not implemented yet', file=sys.stderr)
    return 1


if __name__ == '__main__':
    sys.exit(main())
