"""``truckd`` entry point: dispatches to one module per subcommand.

Only the chosen subcommand's module is imported (``truckd run`` on the car does not load
the offline tools' scipy, matplotlib or the diagnosis stack); ``truckd --help`` and a
missing or unknown command import them all to list them.

Exit codes (reference section 1): 0 success, 2 bad usage or input (one line naming
the file, line or key and what was expected), 1 other failures.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from types import FrameType

import truckd
from truckd.errors import InputError, TruckdError

# Subcommand name -> module with add_subparser(subparsers) and run(args) -> int.
SUBCOMMANDS: dict[str, str] = {
    "params": "truckd.cli.params",
    "simulate": "truckd.cli.simulate",
    "sim": "truckd.cli.sim",
    "monitor": "truckd.cli.monitor",
    "run": "truckd.cli.run",
    "identify": "truckd.cli.identify",
    "diagnose": "truckd.cli.diagnose",
    "recover": "truckd.cli.recover",
    "replay": "truckd.cli.replay",
    "characterize": "truckd.cli.characterize",
}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        # One line (reference section 1); the usage is one --help away.
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(2)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser with ``command``'s subparser only (its module alone is imported), or with
    every subcommand when ``command`` is None or not one of them."""
    parser = _Parser(prog="truckd", description="Model-scale truck controller and tools.")
    parser.add_argument("--version", action="version", version=f"truckd {truckd.version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    chosen = {command: SUBCOMMANDS[command]} if command in SUBCOMMANDS else SUBCOMMANDS
    for name, module in chosen.items():
        importlib.import_module(module).add_subparser(sub)
        assert name in sub.choices, f"{module} must register '{name}'"
        sub.choices[name].set_defaults(command_parser=sub.choices[name])  # its own errors
    return parser


def _more_positionals(args: argparse.Namespace, unknown: list[str]) -> list[str]:
    """Arguments left after the options (``diagnose A.csv --json o.json B.csv``: argparse
    stops ``LOG ...`` at the first option): given to the command's one list-taking
    positional when every one of them is a plain argument; else returned (unknown)."""
    sub = getattr(args, "command_parser", None)
    lists = [
        a
        for a in (sub._actions if sub is not None else [])
        if not a.option_strings and a.nargs in ("+", "*")
    ]
    if len(lists) != 1 or not unknown or any(u.startswith("-") for u in unknown):
        return unknown
    setattr(args, lists[0].dest, [*getattr(args, lists[0].dest), *unknown])
    return []


DEBUG_ENV = "TRUCKD_DEBUG"
"""Set (to anything) to let an unexpected exception's traceback through."""

_OWN_SIGNALS = ("run", "monitor", "characterize")
"""Commands that handle SIGTERM themselves (the daemon stops its loop and the motor)."""


def _terminated(signum: int, _frame: FrameType | None) -> None:
    raise SystemExit(128 + signum)


@contextlib.contextmanager
def _term_unwinds(command: str) -> Iterator[None]:
    """SIGTERM and SIGHUP raise SystemExit(128 + signal) in the main thread while a tool
    runs, so its cleanup runs as on Ctrl-C (no temporary file left half-written; the
    default action kills the process on the spot).  Only where the default action is in
    place: a signal ignored (``nohup`` ignores SIGHUP) stays ignored.  The previous
    handlers come back after."""
    if command in _OWN_SIGNALS or threading.current_thread() is not threading.main_thread():
        yield
        return
    sigs = [s for s in (signal.SIGTERM, signal.SIGHUP) if signal.getsignal(s) is signal.SIG_DFL]
    old = {s: signal.signal(s, _terminated) for s in sigs}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def main(argv: Sequence[str] | None = None) -> int:
    args_list = list(sys.argv[1:] if argv is None else argv)
    if args_list == ["--version"]:  # without importing every command's module to list them
        print(f"truckd {truckd.version()}")
        return 0
    parser = build_parser(args_list[0] if args_list else None)
    try:
        args, unknown = parser.parse_known_args(args_list)
        unknown = _more_positionals(args, unknown)
        before = args_list[: args_list.index(args.command)] if unknown else []
        if any(u in before for u in unknown):  # given to truckd itself, not the command
            parser.error(f"unrecognized arguments: {' '.join(u for u in unknown if u in before)}")
        if unknown:  # named by the command they were given to: `truckd CMD: error: ...`
            args.command_parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    except SystemExit as exc:  # bad usage (one line printed) or --help: a code, not a raise
        return exc.code if isinstance(exc.code, int) else 2
    try:
        with _term_unwinds(args.command):
            code = int(args.run(args))
    except InputError as exc:
        print(f"truckd {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except TruckdError as exc:
        print(f"truckd {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader went away (`truckd params --json | head -1`): nothing more to say, and
        # nothing for the interpreter to flush into the closed pipe at exit.
        with contextlib.suppress(OSError, ValueError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except Exception as exc:  # a bug, or a failure nobody foresaw: one line, not a traceback
        if os.environ.get(DEBUG_ENV):
            raise
        first = (str(exc).strip().splitlines() or [""])[0]  # one line (a build log follows)
        print(
            f"truckd {args.command}: failed: {type(exc).__name__}: {first} "
            f"(set {DEBUG_ENV}=1 for the traceback)",
            file=sys.stderr,
        )
        return 1
    return code


if __name__ == "__main__":
    sys.exit(main())
