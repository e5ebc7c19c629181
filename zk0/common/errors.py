"""The one base class of zk0's user-facing errors, and the command-line parser that reports them.

Each is raised for bad input (a run-config value, a registry entry, a dataset, an asset
request) with a message of one sentence naming the bad value and what was expected, so
entry points can print it as it is instead of a traceback.
"""

import argparse
import sys

# The Flower error code of a reply a client refused with a Zk0Error: its reason is the sentence.
REFUSED = 100


class Zk0Error(ValueError):
    """Bad input, explained in one sentence."""


class OneSentenceParser(argparse.ArgumentParser):
    """argparse, but a bad argument is one sentence (and exit code 2) instead of usage plus an error."""

    def error(self, message: str):
        print(f"{self.prog}: {message}; see {self.prog} --help.", file=sys.stderr)
        sys.exit(2)


def positive(kind: type[int] | type[float]):
    """An argparse ``type``: a number of ``kind`` above 0, or argparse's one-sentence refusal naming it."""

    def parse(text: str) -> int | float:
        try:
            value = kind(text)
        except ValueError:
            value = 0
        if value <= 0:
            raise argparse.ArgumentTypeError(f"got {text!r}; expected {kind.__name__} > 0")
        return value

    return parse
