"""The command lines' parser: argparse with its usage errors on one line."""
from __future__ import annotations

import argparse


class Parser(argparse.ArgumentParser):
    """argparse's parser with a usage error on one line, ``prog: error: message (see prog --help)``, and exit 2 (no
    usage block first); subcommands' parsers are of the same class (argparse's default for ``add_subparsers``). No
    abbreviations: argparse would take ``--depth 0.003`` for ``--depth-limit-m 0.003`` (session 56's review) -- a
    silent change of meaning, so an option is spelt in full or refused."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        message = message.replace("\r", "\\r").replace("\n", "\\n")      # a value with a newline stays one line
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def parse_args(self, args=None, namespace=None):
        """argparse's, with arguments no parser knows refused by the chosen subcommand's parser (so the line names
        ``palpate predict``, not ``palpate``)."""
        ns, extra = self.parse_known_args(args, namespace)
        if extra:
            sub = next((a for a in self._actions if isinstance(a, argparse._SubParsersAction)), None)
            chosen = sub.choices.get(getattr(ns, sub.dest, None)) if sub is not None else None
            (chosen or self).error(f"unrecognized arguments: {' '.join(extra)}")
        return ns
