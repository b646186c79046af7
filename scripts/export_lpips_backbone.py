#!/usr/bin/env python3
"""Export the ImageNet backbone of LPIPS (torchvision's pretrained VGG16 or AlexNet) as a
safetensors file for gdrf's Rust LPIPS (gdrf_core::pretrained::lpips).

    scripts/export_lpips_backbone.py --net vgg|alex OUT.safetensors [--from-pth FILE]

The `lpips` package builds its backbone with torchvision's `vgg16(pretrained=True)` /
`alexnet(pretrained=True)`, i.e. the IMAGENET1K_V1 weights. These are not in the lpips
wheel: torchvision downloads them (about 530 MB for VGG16, 230 MB for AlexNet) into the
torch hub cache (~/.cache/torch/hub/checkpoints/, or $TORCH_HOME), so run this once on a
machine with internet, or where that cache already holds vgg16-397923af.pth /
alexnet-owt-7be5be79.pth, and copy OUT.safetensors over. `--from-pth` reads such a
torchvision checkpoint file from anywhere instead of the cache.

Only the convolutional `features.*` tensors are written (torchvision's names:
`features.0.weight`, `features.0.bias`, …); LPIPS never uses the classifier. The Rust loader
also accepts a full torchvision state dict and skips its `classifier.*` tensors.

The calibrated 1x1 heads come from the lpips wheel: scripts/convert_lpips_heads.py.
"""
import argparse
import os

import torch
import torchvision
from safetensors.torch import save_file

BUILDERS = {
    "vgg": (torchvision.models.vgg16, "VGG16_Weights"),
    "alex": (torchvision.models.alexnet, "AlexNet_Weights"),
}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--net", choices=sorted(BUILDERS), required=True)
    ap.add_argument("out", help="output .safetensors")
    ap.add_argument("--from-pth", help="a torchvision checkpoint (state dict) instead of the download")
    args = ap.parse_args()

    build, weights_enum = BUILDERS[args.net]
    if args.from_pth:
        model = build(weights=None)
        model.load_state_dict(torch.load(args.from_pth, map_location="cpu", weights_only=True))
    else:
        model = build(weights=getattr(torchvision.models, weights_enum).IMAGENET1K_V1)
    features = {k: v.detach().float().contiguous() for k, v in model.state_dict().items() if k.startswith("features.")}
    source = os.path.basename(args.from_pth) if args.from_pth else f"torchvision {torchvision.__version__} {weights_enum}.IMAGENET1K_V1"
    save_file(features, args.out, metadata={"net": args.net, "source": source})
    print(f"{args.out}: {len(features)} tensors")


if __name__ == "__main__":
    main()
