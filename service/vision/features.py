"""Local features (SIFT, optionally CLAHE + RootSIFT) and the papers' similarity m(A, B).

Extraction: SIFT keypoints on the grayscale frame at the map's working size. Two options go
beyond the papers because they survive a change of light (README, "Features across
lighting"): CLAHE (contrast-limited adaptive histogram equalisation) before detection, and
RootSIFT (Arandjelovic & Zisserman 2012: the element-wise square root of the L1-normalised
descriptor, so the angle between RootSIFT vectors is the Hellinger distance of the SIFT
histograms). Descriptors are quantised to uint8 codes (plain SIFT is integer-valued already;
RootSIFT is scaled by ``ROOT_SCALE``), which is what a map stores; matching uses the unit
vectors of those codes, so a map built in memory and the same map loaded from disk match alike.

Journal Sec. 4: the distance between unit descriptors is their angle (arccos of the scalar
product); a in M_AB iff angle(a, b1) / angle(a, b2) < delta for its nearest and second-nearest
neighbours b1, b2 in B; the symmetric matches M*_AB are reciprocal nearest neighbours passing
the test both ways; m(A, B) = |M*_AB| / min(|A|, |B|), 0 when either set is empty.

A ratio test needs a second neighbour, so a set with fewer than two features matches nothing.
One call compares a frame with K map images with a single matrix product (BLAS): the K
descriptor sets are stacked into a zero-padded (K, n_max, D+1) block whose extra column is 0 for
real rows and -4 for padding, against the frame's descriptors with an extra column of 1, so
padding scores -4 (below any angle) without a masking pass.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from functools import cached_property
from typing import TYPE_CHECKING, Any, Protocol, get_args

import cv2
import numpy as np

from service.api.models import MAX_FEATURES_CAP, WORKING_SIDE, FeatureTypeName

if TYPE_CHECKING:
    from typing import TypeAlias

    from service.vision.xfeat import XFeatParams

    FeatureParams: TypeAlias = "SiftParams | XFeatParams | DualParams"  # a map's feature type

DEFAULT_DELTA = 0.6  # ratio threshold delta (journal Sec. 4)
_PAD_SCORE = -4.0
# RootSIFT components are sqrt(L1 share) <= ~0.35 in practice; x512 uses ~7 of the 8 bits
ROOT_SCALE = 512.0


@dataclass(frozen=True)
class SiftParams:
    """OpenCV SIFT settings, the contrast normalisation and the working image size."""

    width: int = 320
    height: int = 240
    # the strongest kept (0: all, OpenCV's default): bounds a comparison's exact matching on
    # rich frames, as XFeat's top_k does (KITTI at full width gives 5,400; docs/research/
    # performance.md, "A cap on features per frame")
    n_features: int = 2048
    contrast_threshold: float = 0.04
    edge_threshold: float = 10.0
    sigma: float = 1.6
    clahe: bool = True  # CLAHE before detection (not in the papers)
    clahe_clip: float = 2.0  # OpenCV clipLimit
    clahe_tile: int = 8  # tiles per image side
    root: bool = True  # RootSIFT descriptors (not in the papers)

    def as_dict(self) -> dict:
        return {"type": "sift", **asdict(self)}

    @classmethod
    def papers(cls, width: int = 320, height: int = 240) -> SiftParams:
        """Plain SIFT as in the papers (no contrast normalisation, no RootSIFT)."""
        return cls(width=width, height=height, n_features=0, clahe=False, root=False)


@dataclass(frozen=True)
class DualParams:
    """Two feature types per frame and map image (``clahe-rootsift+xfeat``): CLAHE + RootSIFT,
    the first, which the two-view geometry and the place index use, and XFeat, the second;
    the map's similarity fuses both (service/vision/fusion.py). One working size for both."""

    sift: SiftParams
    xfeat: XFeatParams

    def __post_init__(self) -> None:
        if (self.sift.width, self.sift.height) != (self.xfeat.width, self.xfeat.height):
            raise ValueError("both feature types of a map need one working size")

    @property
    def width(self) -> int:
        return self.sift.width

    @property
    def height(self) -> int:
        return self.sift.height

    def as_dict(self) -> dict[str, Any]:
        return {"type": DUAL, "sift": self.sift.as_dict(), "xfeat": self.xfeat.as_dict()}


DUAL = "sift+xfeat"  # the metadata type of a map with both (feature type clahe-rootsift+xfeat)


@dataclass(frozen=True)
class Features:
    """Keypoint positions (N, 2) in working-size pixels and descriptor codes (N, D): uint8
    (RootSIFT) or int8 (XFeat). ``second``: the frame's XFeat features where the map holds
    two types (``DualParams``; these are then its RootSIFT ones)."""

    keypoints: np.ndarray
    codes: np.ndarray
    second: Features | None = None

    def __len__(self) -> int:
        return len(self.codes)

    @cached_property
    def descriptors(self) -> np.ndarray:
        """Unit float32 descriptors (the codes' directions), what the similarity compares."""
        return unit_descriptors(self.codes)


def unit_descriptors(codes: np.ndarray) -> np.ndarray:
    """L2-normalised float32 rows of uint8 codes (a zero row stays zero)."""
    d = np.asarray(codes, np.float32)
    norms = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.maximum(norms, 1e-12)


class WorkingSize(Protocol):
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...


def to_working_size(image: np.ndarray, params: WorkingSize) -> np.ndarray:
    """Grayscale uint8 at the map's working size (area interpolation when shrinking)."""
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code)
    if image.dtype != np.uint8:
        raise ValueError(f"expected an 8-bit image, got {image.dtype}")
    h, w = image.shape
    if (w, h) != (params.width, params.height):
        interp = cv2.INTER_AREA if w > params.width else cv2.INTER_LINEAR
        image = cv2.resize(image, (params.width, params.height), interpolation=interp)
    return image


def feature_params(d: dict[str, Any]) -> FeatureParams:
    """The feature parameters a map's metadata ``feature`` describes (``type``: sift, xfeat,
    or sift+xfeat with each one's parameters under ``sift`` and ``xfeat``)."""
    from service.vision.xfeat import XFeatParams

    kind = d.get("type", "sift")
    rest = {k: v for k, v in d.items() if k != "type"}
    if kind == "sift":
        return SiftParams(**rest)
    if kind == "xfeat":
        return XFeatParams(**rest)
    if kind == DUAL:
        sift, xfeat = feature_params(rest["sift"]), feature_params(rest["xfeat"])
        if not isinstance(sift, SiftParams) or not isinstance(xfeat, XFeatParams) or \
                set(rest) != {"sift", "xfeat"}:
            raise ValueError(f"a {DUAL} map describes its sift and xfeat parameters, got {d}")
        return DualParams(sift, xfeat)
    raise ValueError(f"unknown feature type '{kind}' (this swarmloc knows sift, xfeat and "
                     f"{DUAL})")


FEATURE_TYPES: tuple[str, ...] = get_args(FeatureTypeName)  # the CLI's, the API's and the lab's


def named_params(name: str, width: int = 320, height: int = 240,
                 max_features: int | None = None) -> FeatureParams:
    """The feature parameters of a feature type name at a working size: ``clahe-rootsift``
    (CLAHE + RootSIFT, the default), ``sift`` (the papers'), ``xfeat`` or
    ``clahe-rootsift+xfeat`` (both, fused). ``max_features``: SIFT's cap per frame and map
    image (``SiftParams.n_features``; 0 keeps all; None: the type's default); XFeat keeps its
    own (``top_k``)."""
    from service.vision.xfeat import XFeatParams

    lo, hi = WORKING_SIDE
    if not (lo <= width <= hi and lo <= height <= hi):
        raise ValueError(f"the working size must be {lo}-{hi} pixels a side, got "
                         f"{width}x{height}")
    if max_features is not None and not 0 <= max_features <= MAX_FEATURES_CAP:
        raise ValueError(f"max_features must be from 0 (all) to {MAX_FEATURES_CAP}, got "
                         f"{max_features}")
    sift = SiftParams(width=width, height=height)
    if name == "sift":
        sift = SiftParams.papers(width, height)
    if max_features is not None:
        sift = replace(sift, n_features=max_features)
    if name in ("clahe-rootsift", "sift"):
        return sift
    if name == "xfeat":
        if max_features is not None:
            raise ValueError("max_features caps SIFT's features; XFeat keeps its own "
                             f"{XFeatParams().top_k} (top_k)")
        return XFeatParams(width=width, height=height)
    if name == "clahe-rootsift+xfeat":
        return DualParams(sift, XFeatParams(width=width, height=height))
    raise ValueError(f"unknown feature type {name!r}; choose one of {list(FEATURE_TYPES)}")


def sift_cap(params: FeatureParams) -> int | None:
    """SIFT's features kept per image under ``params`` (0: all; None: XFeat alone)."""
    sift = params.sift if isinstance(params, DualParams) else params
    return sift.n_features if isinstance(sift, SiftParams) else None


def extract(image: np.ndarray, params: FeatureParams | None = None) -> Features:
    """Keypoints and descriptor codes of a frame (resized to the working size): CLAHE +
    RootSIFT (uint8 codes), XFeat (int8 codes, service/vision/xfeat.py) or both (the
    RootSIFT ones with the XFeat ones as ``second``; the frame is resized once)."""
    params = params or SiftParams()
    gray = to_working_size(image, params)
    if isinstance(params, DualParams):
        return replace(_extract_gray(gray, params.sift),
                       second=_extract_gray(gray, params.xfeat))
    return _extract_gray(gray, params)


def _extract_gray(gray: np.ndarray, params: SiftParams | XFeatParams) -> Features:
    if not isinstance(params, SiftParams):
        from service.vision.xfeat import extract_xfeat

        return Features(*extract_xfeat(gray, params))
    if params.clahe:
        tiles = (params.clahe_tile, params.clahe_tile)
        gray = cv2.createCLAHE(clipLimit=params.clahe_clip, tileGridSize=tiles).apply(gray)
    sift = cv2.SIFT_create(  # cheap to create; one per call keeps threads independent
        nfeatures=params.n_features,
        contrastThreshold=params.contrast_threshold,
        edgeThreshold=params.edge_threshold,
        sigma=params.sigma,
    )
    kps, desc = sift.detectAndCompute(gray, None)
    if desc is None or len(kps) == 0:
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.uint8))
    desc = np.asarray(desc, np.float32)
    if params.root:
        total = desc.sum(axis=1, keepdims=True)
        desc = np.sqrt(desc / np.maximum(total, 1e-12)) * ROOT_SCALE
    codes = np.clip(np.rint(desc), 0, 255).astype(np.uint8)
    keep = codes.any(axis=1)
    pts = np.array([kp.pt for kp in kps], np.float32)[keep]
    return Features(pts, codes[keep])


def _angles(dots: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip(dots, -1.0, 1.0))


_TIE = 2e-7  # float32 dots of two identical rows may differ by rounding (GEMM kernels)


def _ratio_pass(best: np.ndarray, second: np.ndarray, delta: float) -> np.ndarray:
    """angle(best) / angle(second) < delta, written without a division (0/0 never passes);
    a tie (the second as close as the best, up to float32 rounding) never passes."""
    return (_angles(best) < delta * _angles(second)) & (best - second > _TIE)


@dataclass(frozen=True)
class BatchMatch:
    """Result of comparing one frame A with K sets B_k."""

    counts: np.ndarray  # (K,) |M*_AB_k|
    scores: np.ndarray  # (K,) m(A, B_k)
    matched: np.ndarray  # (K, |A|) bool: feature a of A is in a symmetric match with B_k


def match_batch(a: np.ndarray, sets: Sequence[np.ndarray], delta: float = DEFAULT_DELTA
                ) -> BatchMatch:
    """Symmetric ratio-test matches of descriptors ``a`` (nA, D) against each of ``sets``."""
    k = len(sets)
    na = len(a)
    nb = np.array([len(b) for b in sets], np.int64)
    if k == 0 or na == 0 or nb.max(initial=0) == 0:
        return BatchMatch(np.zeros(k, np.int64), np.zeros(k), np.zeros((k, na), bool))
    dim = a.shape[1]
    n_max = int(nb.max())
    block = np.zeros((k, n_max, dim + 1), np.float32)
    block[:, :, dim] = _PAD_SCORE
    for i, b in enumerate(sets):
        block[i, : len(b), :dim] = b
        block[i, : len(b), dim] = 0.0
    a_aug = np.empty((na, dim + 1), np.float32)
    a_aug[:, :dim] = a
    a_aug[:, dim] = 1.0
    # S[k, j, i] = <b_kj, a_i>, one GEMM for all K sets
    s = (block.reshape(k * n_max, dim + 1) @ a_aug.T).reshape(k, n_max, na)

    # B_k -> A: nearest a (i1) and the two best scores for every b (contiguous axis 2)
    i1 = s.argmax(axis=2)
    s1 = np.take_along_axis(s, i1[:, :, None], axis=2)
    np.put_along_axis(s, i1[:, :, None], -np.inf, axis=2)
    s2 = s.max(axis=2) if na > 1 else np.full((k, n_max), _PAD_SCORE, np.float32)
    np.put_along_axis(s, i1[:, :, None], s1, axis=2)
    s1 = s1[:, :, 0]
    valid_b = np.arange(n_max)[None, :] < nb[:, None]
    pass_ba = _ratio_pass(s1, s2, delta) & valid_b & (na >= 2)

    # A -> B_k: best score t1 of every a (axis 1). b_kj and a_i1 are reciprocal nearest
    # neighbours iff s1[k, j] == t1[k, i1]; ties cannot pass a ratio test (angle ratio 1), so
    # no argmax over the strided axis is needed.
    t1 = s.max(axis=1)
    t1_at_b = np.take_along_axis(t1, i1, axis=1)
    reciprocal = valid_b & (s1 == t1_at_b)
    # second-best b for each a: hide the reciprocal partner, take the max again
    kk, jj = np.nonzero(reciprocal)
    ii = i1[kk, jj]
    s[kk, jj, ii] = -np.inf
    t2 = s.max(axis=1)
    pass_ab = np.zeros((k, na), bool)
    # an exact tie (two partners with one score) is an angle ratio of 1: never a match
    unique = np.bincount(kk * na + ii, minlength=k * na)[kk * na + ii] == 1
    pass_ab[kk, ii] = _ratio_pass(t1[kk, ii], t2[kk, ii], delta) & (nb[kk] >= 2) & unique
    # a pair counts when both directions pass: mark a in the sets where its partner passes too
    matched = np.zeros((k, na), bool)
    both = pass_ab[kk, ii] & pass_ba[kk, jj]
    matched[kk[both], ii[both]] = True
    counts = matched.sum(axis=1)
    denom = np.minimum(na, nb)
    scores = np.where(denom > 0, counts / np.maximum(denom, 1), 0.0)
    return BatchMatch(counts, scores, matched)


def similarity(a: np.ndarray, b: np.ndarray, delta: float = DEFAULT_DELTA) -> float:
    """m(A, B) for two descriptor sets (journal Sec. 4)."""
    return float(match_batch(a, [b], delta).scores[0])


def similarity_bfmatcher(a: np.ndarray, b: np.ndarray, delta: float = DEFAULT_DELTA
                         ) -> tuple[int, float]:
    """Reference: the same m(A, B) with OpenCV BFMatcher.knnMatch(k=2) both ways.

    L2 distances between unit vectors are turned into angles (2 asin(d / 2)) for the ratio test.
    Used by the benchmark and the tests; the service uses ``match_batch``.
    """
    if len(a) == 0 or len(b) == 0:
        return 0, 0.0
    bf = cv2.BFMatcher(cv2.NORM_L2)

    def one_way(q: np.ndarray, t: np.ndarray) -> dict[int, int]:
        out: dict[int, int] = {}
        if len(t) < 2:
            return out
        for pair in bf.knnMatch(q, t, k=2):
            m1, m2 = pair
            th1 = 2 * np.arcsin(min(m1.distance / 2, 1.0))
            th2 = 2 * np.arcsin(min(m2.distance / 2, 1.0))
            if th1 < delta * th2:
                out[m1.queryIdx] = m1.trainIdx
        return out

    ab, ba = one_way(a, b), one_way(b, a)
    count = sum(1 for i, j in ab.items() if ba.get(j) == i)
    return count, count / min(len(a), len(b))
