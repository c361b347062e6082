"""The ``lasercal`` command: one sub-command per module in ``app.commands``.

Every sub-command module exposes ``register(subparsers)``; it adds its parser and sets
``func`` (called with the parsed namespace, returns the exit status). Errors derived from
:class:`calib_core.errors.LasercalError` become one ``error:`` line on stderr and exit 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

from calib_core.errors import LasercalError

#: Sub-command modules, in the order ``--help`` lists them.
COMMANDS: tuple[str, ...] = ("solve", "serve", "acquire", "export", "platform", "measure",
                             "sensor", "robot", "emulate", "report", "camera")


def one_line(text: str) -> str:
    """``text`` with control characters (newlines, CR, ...) escaped, so it stays on one line."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class ArgumentParser(argparse.ArgumentParser):
    """argparse that reports a usage error as one ``error:`` line and exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        sys.stderr.write(f"error: {one_line(f'{self.prog}: {message}')} (see --help)\n")
        raise SystemExit(2)


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(
        prog="lasercal",
        description=(
            "Calibrate a laser displacement sensor carried by a robot (beam point T and "
            "direction u' in the flange frame) and measure with it. Units: mm and degrees."
        ),
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=ArgumentParser)
    sub.required = True
    for name in COMMANDS:
        importlib.import_module(f"app.commands.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``lasercal`` console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except LasercalError as exc:
        sys.stderr.write(f"error: {one_line(str(exc))}\n")
        return 2
    except BrokenPipeError:  # e.g. piped into `head`: the reader has what it wanted
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        sys.stderr.write("error: interrupted\n")
        return 130
    except Exception as exc:  # last line of defence: never a traceback for the operator
        if os.environ.get("LASERCAL_DEBUG"):
            raise
        sys.stderr.write(f"error: internal failure ({one_line(f'{type(exc).__name__}: {exc}')}"
                         "); rerun with LASERCAL_DEBUG=1 for details\n")
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
