"""Memory and time of a map's image cache under a budget: two frames of a round compared with
every image of a map, then the process's RSS growth, the cache's bytes and values, how many
were made (an image dropped and compared again is made again) and the time per comparison.

    PYTHONPATH=. python scripts/image_cache_memory.py MAP.swmap ROUND_DIR BUDGET_MIB
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from client.dataset import read_round
from service.maps.route_map import load_map
from service.vision.features import extract


def rss_mb() -> float:
    status = Path("/proc/self/status").read_text()
    return int(status.split("VmRSS:")[1].split()[0]) / 1024


def main() -> None:
    map_path, round_dir, budget_mib = sys.argv[1], sys.argv[2], int(sys.argv[3])
    m = load_map(map_path, verify="lazy")
    m.image_cache.limit_bytes = budget_mib * 2**20
    rnd = read_round(round_dir)
    frames = [extract(rnd.load_image(i), m.feature_params) for i in (0, len(rnd) // 2)]
    before, t0 = rss_mb(), time.perf_counter()
    for f in frames:
        for a in range(0, m.n_images, 20):
            m.similarity(f, list(range(a, min(a + 20, m.n_images))))
    took = time.perf_counter() - t0
    c = m.image_cache
    print(f"budget {budget_mib} MiB: RSS +{rss_mb() - before:.0f} MB after comparing "
          f"{len(frames)} frames with all {m.n_images} images; cache {c.bytes / 2**20:.0f} MB "
          f"in {len(c)} values, {c.made} made; "
          f"{took / (len(frames) * m.n_images) * 1e3:.2f} ms per comparison")


if __name__ == "__main__":
    main()
