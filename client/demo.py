"""The demo map: a recipe that renders one round of the synthetic world and builds a map."""

from __future__ import annotations

import tempfile
from pathlib import Path

from client.dataset import read_round
from client.world import World
from service.route_map import build_map, list_maps, save_map

DEMO_SEED = 0
DEMO_LENGTH_M = 260.0


def ensure_demo_map(maps_dir: Path, name: str = "demo", progress: bool = True) -> Path:
    """Build ``maps_dir/NAME.swmap`` from the sunny1 round of the default world if missing."""
    path = maps_dir / f"{name}.swmap"
    if path in list_maps(maps_dir):
        return path
    world = World(DEMO_SEED, DEMO_LENGTH_M)
    with tempfile.TemporaryDirectory() as tmp:
        rnd_dir = world.render_round(Path(tmp) / "sunny1", 0, "sunny", progress=progress)
        rnd = read_round(rnd_dir)
        m = build_map(name, [rnd.load_image(i) for i in range(len(rnd))], rnd.xy,
                      list(rnd.images),
                      source={"world_seed": DEMO_SEED, "round": "sunny1", "condition": "sunny"})
    return save_map(m, path)
