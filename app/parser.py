"""The command lines' parser: argparse with its usage errors on one line."""
from __future__ import annotations

import argparse


class Parser(argparse.ArgumentParser):
    """argparse's parser with a usage error on one line, ``prog: error: message (see prog --help)``, and exit 2 (no
    usage block first); subcommands' parsers are of the same class (argparse's default for ``add_subparsers``)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")
