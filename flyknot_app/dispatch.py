"""Running a parsed command: errors of the FlyknotError family become one line, exit 2.

Shared by every command-line entry point (``flyknot``, ``flyknot demo``, ``flyknot-tools``).
"""

from __future__ import annotations

import argparse
import sys

from flyknot.errors import FlyknotError


def dispatch(args: argparse.Namespace, prog: str = "flyknot") -> int:
    """Run a parsed command; errors of the FlyknotError family become one line, exit 2.

    Args:
        args: Parsed arguments whose ``func`` runs the command.
        prog: Program name the messages start with.
    """
    try:
        return int(args.func(args) or 0)
    except FlyknotError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
