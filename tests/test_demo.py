"""`serve --demo` builds its map from the round shipped in service/demo (no renderer)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.api.models import DEFAULT_FEATURES
from service.demo import demo_round, ensure_demo_map
from service.engine.localizer import Localizer
from service.maps.route_map import load_map
from service.vision.features import DUAL


def test_demo_map_is_built_once_from_the_shipped_round(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture) -> None:
    path = ensure_demo_map(tmp_path / "maps", progress=True)
    assert "building the demo map" in capsys.readouterr().err  # the progress bar
    m = load_map(path)
    rnd = demo_round()
    assert m.name == "demo" and m.n_images == len(rnd) == 67
    np.testing.assert_allclose(m.positions, rnd.xy)
    assert m.meta["source"]["world_seed"] == 0
    assert m.meta["feature"]["type"] == DUAL and DEFAULT_FEATURES == "clahe-rootsift+xfeat"
    stamp = path.stat().st_mtime_ns
    assert ensure_demo_map(tmp_path / "maps", progress=True) == path and \
        path.stat().st_mtime_ns == stamp
    assert capsys.readouterr().err == ""  # nothing built, no bar
    # a shipped frame is found where it was taken
    loc = Localizer(m, "dpso", seed=0)
    for _ in range(5):
        est = loc.localize(rnd.load_image(30), t=None)
    assert np.hypot(est.x - rnd.xy[30, 0], est.y - rnd.xy[30, 1]) < 3.0
