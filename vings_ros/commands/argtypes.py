"""argparse value types shared by the commands (errors name the option, no traceback)."""
from __future__ import annotations

import argparse
from typing import Callable


def int_at_least(lo: int) -> Callable[[str], int]:
    """An argparse ``type``: an integer ``>= lo``."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be >= {lo}, got {v}")
        return v
    return parse


#: largest working image side accepted on the command line (an extra zero would otherwise ask for
#: hundreds of GB before failing deep inside OpenCV or the ray caster)
MAX_IMAGE_SIDE = 8192


def int_in_range(lo: int, hi: int) -> Callable[[str], int]:
    """An argparse ``type``: an integer in ``[lo, hi]``."""
    at_least = int_at_least(lo)

    def parse(text: str) -> int:
        v = at_least(text)
        if v > hi:
            raise argparse.ArgumentTypeError(f"must be <= {hi}, got {v}")
        return v
    return parse


def image_side(text: str) -> int:
    """An argparse ``type``: an image width or height in pixels, ``1..MAX_IMAGE_SIDE``."""
    return int_in_range(1, MAX_IMAGE_SIDE)(text)
