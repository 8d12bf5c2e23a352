"""
The ``rotor-id`` command line.

Run it from a clone with ``./rotor-id <command>`` (no sourcing needed) or, in a sourced
workspace, as ``ros2 run rotor_id rotor-id <command>``. Each command lives in its own module
under :mod:`rotor_id.commands` with ``add_arguments(parser)`` and ``run(args) -> int``.

Errors a user can act on (bad bag, bad run description, unidentifiable problem) end the command
with one line on stderr and exit code 2; an unexpected failure prints one line and the hint to
re-run with ``--debug`` for the traceback (exit code 3).
"""

import argparse
import atexit
import importlib
import importlib.util
import os
import sys
import threading
from typing import NoReturn, Sequence

#: command name -> (module, one-line help)
COMMANDS = {
    'demo': ('rotor_id.commands.demo',
             'start the five nodes on the simulated rotor, identify it live and offline'),
    'identify': ('rotor_id.commands.identify',
                 'identify model parameters from a bag (output-error ML by default)'),
    'frequency-response': ('rotor_id.commands.frequency_response',
                           'directional frequency response of the flap to the stirring, with '
                           'coherence and the model overlaid'),
    'diagnose': ('rotor_id.commands.diagnose',
                 'locate and explain where a recording and the model disagree'),
    'campaign': ('rotor_id.commands.campaign',
                 'identify (and diagnose) every bag of a test campaign: table, report, trends'),
    'plan': ('rotor_id.commands.plan',
             'predict the accuracy of candidate stirring transients before a run'),
    'reproduce-report': ('rotor_id.commands.reproduce_report',
                         "run the report's cases and print our numbers beside the report's"),
}


def _user_errors():
    errors = [ValueError, FileNotFoundError, PermissionError, KeyError]
    return tuple(errors)


def _available(module_name):
    return importlib.util.find_spec(module_name) is not None


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """
    Return the argument parser with one subcommand per available command module.

    Only the ``selected`` command's module is imported (all when None), so ``rotor-id
    identify`` does not pay for the imports of ``reproduce-report`` or ``demo``.
    """
    parser = argparse.ArgumentParser(
        prog='rotor-id', description='Identify rotor flapping dynamics from transient tests.')
    parser.add_argument('--debug', action='store_true',
                        help='show the full traceback of an unexpected error')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    for name, (module_name, help_text) in COMMANDS.items():
        if not _available(module_name):
            continue
        command = sub.add_parser(name, help=help_text, description=help_text)
        if selected is None or name == selected:
            module = importlib.import_module(module_name)
            module.add_arguments(command)
            command.set_defaults(run_command=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` and run the chosen command; return the exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    chosen = next((a for a in argv if not a.startswith('-')), None)
    parser = build_parser(chosen if chosen in COMMANDS else None)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    from rotor_id.commands.common import capture_warnings
    try:
        with capture_warnings():
            return int(args.run_command(args) or 0)
    except KeyboardInterrupt:
        print(f'rotor-id {args.command}: interrupted', file=sys.stderr)
        return 130
    except BrokenPipeError as exc:
        if not _stdout_closed():
            return _unexpected(args, exc)
        return 128 + 13               # the reader of our output left (`| head`): as SIGPIPE
    except _user_errors() as exc:
        if args.debug:
            raise
        message = str(exc).strip() or type(exc).__name__
        print(f'rotor-id {args.command}: error: {message}', file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: B902 - the last line of defence: one line, not a traceback
        return _unexpected(args, exc)


def _unexpected(args: argparse.Namespace, exc: Exception) -> int:
    """Say an unexpected failure in one line (its traceback with --debug); return 3."""
    if args.debug:
        raise exc
    print(f'rotor-id {args.command}: unexpected {type(exc).__name__}: {exc} '
          '(re-run with --debug for the traceback and please report it)', file=sys.stderr)
    return 3


def _stdout_closed() -> bool:
    """Say whether standard output's reader has gone; if so, point it at /dev/null for exit."""
    import select
    try:
        fd = sys.stdout.fileno()
        poll = select.poll()
        poll.register(fd, select.POLLOUT)
        gone = any(event & select.POLLERR for _, event in poll.poll(0))   # a pipe, no reader
    except (OSError, ValueError, AttributeError):
        return False
    if gone:             # the interpreter flushes stdout at exit: that must not fail again
        os.dup2(os.open(os.devnull, os.O_WRONLY), fd)
    return gone


def exit_with(code: int) -> NoReturn:
    """
    End the process with ``code``, skipping the interpreter's teardown of its modules.

    The at-exit functions run and the standard streams are flushed as at any exit; what is
    skipped is freeing every object one by one, which the system does at once. Where
    another thread is alive the exit is the ordinary one, which waits for it.
    """
    if threading.active_count() > 1:
        sys.exit(code)
    atexit._run_exitfuncs()      # (CPython's own call at exit; no public name)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):       # a reader that left, a closed stream
            pass
    os._exit(code)


def entry() -> NoReturn:
    """Run the console script: :func:`main` on the process's arguments, then :func:`exit_with`."""
    exit_with(main())


if __name__ == '__main__':
    entry()
