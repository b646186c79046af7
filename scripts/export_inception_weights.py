#!/usr/bin/env python3
"""Write the weights of FID's Inception-v3 as safetensors for gdrf's Rust extractor
(gdrf_core::pretrained::inception::InceptionV3).

    scripts/export_inception_weights.py OUT.safetensors
    scripts/export_inception_weights.py OUT.safetensors --from-pth pt_inception-2015-12-05-6726825d.pth

It builds pytorch-fid's `InceptionV3([3])` (`use_fid_inception=True`, the network every
published FID is computed with) and saves that module's state dict: float tensors only
(BatchNorm's integer `num_batches_tracked` counters are left out), contiguous, under the
module's own names (`blocks.0.0.conv.weight` …).

Where the weights come from: without --from-pth, pytorch-fid downloads
pt_inception-2015-12-05-6726825d.pth from its GitHub release (FID_WEIGHTS_URL in
pytorch_fid/inception.py), so this needs internet access once (torch caches the file under
~/.cache/torch/hub/checkpoints). With --from-pth FILE an already downloaded copy of that file
is loaded instead, exactly as pytorch-fid loads the download, and nothing is fetched.

Licence caveat: these are not gdrf's weights and gdrf does not distribute them. They are
Google's Inception-v3 released with TensorFlow (inception-2015-12-05.tgz, the graph of the
original TTUR FID code), ported to PyTorch by pytorch-fid (Apache-2.0), and trained on
ImageNet, whose terms of access restrict use of the data; check that the terms of both fit
your use before redistributing the exported file.
"""
import argparse

import torch
import pytorch_fid.inception as pfi
from safetensors.torch import save_file


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="safetensors file to write")
    ap.add_argument("--from-pth", metavar="FILE",
                    help="a downloaded pt_inception-2015-12-05-6726825d.pth (no network access)")
    args = ap.parse_args()

    if args.from_pth:
        # fid_inception_v3() loads whatever this returns into the patched torchvision model.
        state = torch.load(args.from_pth, map_location="cpu", weights_only=True)
        pfi.load_state_dict_from_url = lambda *a, **k: state
    model = pfi.InceptionV3([pfi.InceptionV3.DEFAULT_BLOCK_INDEX], use_fid_inception=True).eval()
    tensors = {k: v.detach().float().contiguous() for k, v in model.state_dict().items() if v.is_floating_point()}
    save_file(tensors, args.out, metadata={"source": "pytorch-fid InceptionV3([3]), pt_inception-2015-12-05"})
    n = sum(t.numel() for t in tensors.values())
    print(f"wrote {len(tensors)} tensors ({n / 1e6:.1f} M parameters) to {args.out}")


if __name__ == "__main__":
    main()
