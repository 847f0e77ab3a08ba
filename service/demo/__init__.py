"""The demo map, built from the round shipped in this package (service/demo/round).

The round is frame 0 to 66 of ``sunny1`` of the synthetic world (seed 0, 80 m loop, a frame
every 1.2 m; JPEG quality 80), written by ``swarmloc world render`` (``client/lab/``): the
service builds the demo map from it with its own map builder, without the renderer.
Replay a round of the same world against it:
``swarmloc world render data/demo --length 80 --rounds cloudy1``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Iterable, Iterator

    import numpy as np

    from service.maps.round_archive import UploadedRound

DEMO_ROUND_DIR = Path(__file__).resolve().parent / "round"
DEMO_SOURCE = {"world_seed": 0, "length_m": 80.0, "spacing_m": 1.2, "round": "sunny1",
               "condition": "sunny"}
DEMO_HFOV_DEG = 65.0  # the synthetic world's camera (client/lab/world), 320 x 240 pixels


def demo_round(path: Path = DEMO_ROUND_DIR) -> UploadedRound:
    """The shipped round (read like a round uploaded for a build)."""
    from service.api.round_format import POSES_FILE, camera_from_hfov, parse_positions
    from service.maps.round_archive import UploadedRound

    names, xy, t, origin = parse_positions(path / POSES_FILE, None)
    return UploadedRound("sunny1", path, tuple(names), xy, t, origin, max_pixels=320 * 240,
                         camera=camera_from_hfov(DEMO_HFOV_DEG, 320, 240))


def ensure_demo_map(maps_dir: Path, name: str = "demo", progress: bool = False) -> Path:
    """Build ``maps_dir/NAME.swmap`` from the shipped round if it is missing; ``progress``:
    a progress bar on stderr while the features are extracted (about 10 s)."""
    from service.api.models import DEFAULT_FEATURES
    from service.maps.route_map import build_map_from_rounds, list_maps, save_map
    from service.vision.features import named_params

    path = maps_dir / f"{name}.swmap"
    if path in list_maps(maps_dir):
        return path
    rnd = demo_round()

    def bar(images: Iterator[np.ndarray]) -> Iterable[np.ndarray]:
        from tqdm import tqdm

        return tqdm(images, total=len(rnd), desc=f"building the demo map {path}",
                    unit="image", disable=not progress)

    m = build_map_from_rounds([rnd], name=name, source=dict(DEMO_SOURCE), wrap=bar,
                              params=named_params(DEFAULT_FEATURES))
    return save_map(m, path)
