"""argparse types that check numbers as the command line is parsed, and a parser whose errors are one line.

A value out of range is an argparse error (exit code 2, no traceback) before any work starts: a negative seed or
match budget would otherwise run a whole mapping and fail every query one by one.
"""
from __future__ import annotations

import argparse
import math


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line, ``prog: error: message (see prog --help)``, exit code 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None


def _float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return v


def int_at_least(lo: int):
    """An argparse type: an integer >= ``lo``."""

    def parse(text: str) -> int:
        v = _int(text)
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be an integer >= {lo}, got {text!r}")
        return v

    parse.__name__ = f"integer >= {lo}"
    return parse


def float_at_least(lo: float, strict: bool = False):
    """An argparse type: a finite number >= ``lo`` (> ``lo`` when ``strict``)."""

    def parse(text: str) -> float:
        v = _float(text)
        if v < lo or (strict and v == lo):
            raise argparse.ArgumentTypeError(f"must be a number {'>' if strict else '>='} {lo:g}, got {text!r}")
        return v

    parse.__name__ = f"number {'>' if strict else '>='} {lo:g}"
    return parse


def number_list(lo: float = 0.0, strict: bool = True, count=None, usage: str = "numbers separated by commas"):
    """An argparse type: comma-separated finite numbers, each > ``lo`` (>= when not ``strict``), ``count`` of them
    (any number when None), as a tuple; ``usage`` says what is expected."""
    one = float_at_least(lo, strict)

    def parse(text: str) -> tuple:
        try:
            vals = tuple(one(p.strip()) for p in text.split(","))
        except argparse.ArgumentTypeError:
            vals = ()
        if not vals or (count is not None and len(vals) != count):
            raise argparse.ArgumentTypeError(f"takes {usage}, got {text!r}")
        return vals

    parse.__name__ = usage
    return parse

