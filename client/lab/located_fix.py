"""The command line shared by the lab scripts that locate a rendered round's frames at a
map's images (scripts/located_pull.py, scripts/located_rotation.py)."""

from __future__ import annotations

import argparse
from pathlib import Path


def located_fix_parser(doc: str) -> argparse.ArgumentParser:
    """WORLD ROUND, ``--map`` (the round the map is built from), ``--step`` (every n-th
    frame), ``--frames`` (the first n) and ``--features`` (the map's feature type)."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("world", type=Path)
    ap.add_argument("round")
    ap.add_argument("--map", default="sunny1", help="the round the map is built from")
    ap.add_argument("--step", type=int, default=4)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--features", default="clahe-rootsift+xfeat")
    return ap
