#!/usr/bin/env python3
"""Convert the calibrated LPIPS v0.1 heads that ship inside the `lpips` wheel into
safetensors files for gdrf's Rust LPIPS (gdrf_core::pretrained::lpips).

    scripts/convert_lpips_heads.py OUTDIR

writes OUTDIR/lpips-vgg-heads.safetensors and OUTDIR/lpips-alex-heads.safetensors from the
installed package's lpips/weights/v0.1/{vgg,alex}.pth. Tensor names are kept as in the .pth
(`lin0.model.1.weight` … `lin4.model.1.weight`, each (1, C, 1, 1)). The heads are
BSD-2-Clause (Copyright (c) 2018, Richard Zhang, Phillip Isola, Alexei A. Efros, Eli
Shechtman, Oliver Wang); the files' metadata records the source and licence.

The backbones are not in the wheel: see scripts/export_lpips_backbone.py.
"""
import os
import sys
from importlib.metadata import version as package_version

import lpips
import torch
from safetensors.torch import save_file

NETS = ("vgg", "alex")


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    root = os.path.join(os.path.dirname(os.path.abspath(lpips.__file__)), "weights", "v0.1")
    version = package_version("lpips")
    for net in NETS:
        src = os.path.join(root, f"{net}.pth")
        state = torch.load(src, map_location="cpu", weights_only=True)
        heads = {k: v.detach().float().contiguous() for k, v in state.items()}
        meta = {"source": f"lpips {version} weights/v0.1/{net}.pth", "license": "BSD-2-Clause"}
        dst = os.path.join(out, f"lpips-{net}-heads.safetensors")
        save_file(heads, dst, metadata=meta)
        print(f"{dst}: {len(heads)} tensors")


if __name__ == "__main__":
    main()
