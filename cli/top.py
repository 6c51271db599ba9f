"""``tether top``: placeholder replaced below."""
from __future__ import annotations
import argparse
def add_parser(sub: argparse._SubParsersAction) -> None:
    pass
