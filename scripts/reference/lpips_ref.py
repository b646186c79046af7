#!/usr/bin/env python3
"""Reference LPIPS v0.1 from the `lpips` package, for tests/eval_lpips.rs.

    scripts/reference/lpips_ref.py OUTDIR

For net in (vgg, alex): `lpips.LPIPS(net=net, pnet_rand=True, version='0.1')` with a fixed
seed, i.e. a random torchvision backbone (no download needed) under the package's shipped
heads. The conv biases are redrawn at random too (torchvision's VGG init zeroes them), so a
bias that is loaded wrongly shows. Writes, per net:

    {net}-backbone.safetensors  the backbone in torchvision's names (features.0.weight, …)
    {net}-heads.safetensors     lin0.model.1.weight … lin4.model.1.weight
    {net}-case.safetensors      for each size S in (64x64, 48x40): x.S, y.S (B, 3, H, W) in
                                [-1, 1], expected.distance.S (B,) and expected.grad_x.S, the
                                gradient of sum(distance) with respect to x
"""
import os
import re
import sys
import warnings

import lpips
import torch
from safetensors.torch import save_file

SIZES = {"64x64": (3, 64, 64), "48x40": (2, 48, 40)}


def main():
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    torch.set_grad_enabled(True)
    for i, net in enumerate(("vgg", "alex")):
        torch.manual_seed(1234 + i)
        with warnings.catch_warnings():
            # torchvision's deprecation notice for lpips's `pretrained=False`.
            warnings.simplefilter("ignore")
            model = lpips.LPIPS(net=net, pnet_rand=True, version="0.1", verbose=False)
        backbone = {}
        for name, t in model.net.state_dict().items():
            # lpips keeps torchvision's indices inside its slices: slice2.5.weight is features.5.weight.
            m = re.fullmatch(r"slice\d+\.(\d+)\.(weight|bias)", name)
            assert m, name
            if m.group(2) == "bias":
                with torch.no_grad():
                    t.uniform_(-0.1, 0.1)
            backbone[f"features.{m.group(1)}.{m.group(2)}"] = t.detach().clone()
        heads = {k: v.detach().clone() for k, v in model.state_dict().items() if re.fullmatch(r"lin\d\.model\.1\.weight", k)}
        assert len(heads) == 5, sorted(heads)

        case = {}
        for tag, (b, h, w) in SIZES.items():
            x = torch.rand(b, 3, h, w) * 2 - 1
            # A different amount of noise per image, so that a mix-up within the batch shows.
            sigma = torch.linspace(0.1, 0.8, b).view(b, 1, 1, 1)
            y = (x + sigma * torch.randn(b, 3, h, w)).clamp(-1, 1)
            xg = x.clone().requires_grad_(True)
            d = model(xg, y)  # (B, 1, 1, 1)
            d.sum().backward()
            case[f"x.{tag}"] = x
            case[f"y.{tag}"] = y
            case[f"expected.distance.{tag}"] = d.detach().flatten()
            case[f"expected.grad_x.{tag}"] = xg.grad
        save_file(backbone, os.path.join(out, f"{net}-backbone.safetensors"))
        save_file(heads, os.path.join(out, f"{net}-heads.safetensors"))
        save_file({k: v.contiguous() for k, v in case.items()}, os.path.join(out, f"{net}-case.safetensors"))


if __name__ == "__main__":
    main()
