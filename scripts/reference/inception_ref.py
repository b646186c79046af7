"""PyTorch reference of FID's Inception-v3 feature extractor: pytorch-fid's own
`InceptionV3([3])` (`use_fid_inception=True`, i.e. the FIDInceptionA/C/E_1/E_2 blocks of the
TensorFlow 2015-12-05 port) with RANDOM weights, so nothing is downloaded.

    inception_ref.py OUTDIR [--weights-only]

writes OUTDIR/weights.safetensors (the module's float state dict, under pytorch-fid's
names) and, unless --weights-only, OUTDIR/case.safetensors: for each case NAME,
`input.NAME` (B, 3, H, W) images in [-1, 1] and `expected.NAME` (B, 2048) pool3 features,
computed as pytorch-fid computes them: `model((x + 1) / 2)[0]` with resizing to 299² and
normalisation to [-1, 1] on. Float32 throughout.
"""
import argparse
import os

import torch
import torch.nn.functional as F
import pytorch_fid.inception as pfi
from safetensors.torch import save_file

# Input sizes: smaller than 299 (upsampled), exactly 299 (no-op resize), non-square, and
# larger than 299 (downsampled, where the antialias flag would matter).
CASES = {"sq64": (3, 64, 64), "sq299": (1, 299, 299), "wide": (2, 40, 72), "big": (1, 360, 330)}


def build_random_inception():
    """pytorch-fid's InceptionV3([3]) built by its own code, with the download replaced by
    the freshly initialised model's own state dict (a no-op load)."""
    built = {}
    make_torchvision = pfi._inception_v3

    def record(*args, **kwargs):
        built["model"] = make_torchvision(*args, **kwargs)
        return built["model"]

    pfi._inception_v3 = record
    # fid_inception_v3() swaps the FID blocks into the recorded model before loading.
    pfi.load_state_dict_from_url = lambda *a, **k: built["model"].state_dict()
    model = pfi.InceptionV3([pfi.InceptionV3.DEFAULT_BLOCK_INDEX], resize_input=True, normalize_input=True)
    assert type(model.blocks[3][2]).__name__ == "FIDInceptionE_2"
    return model


@torch.no_grad()
def randomise_batchnorm(model, calib, gen):
    """Random BN affine parameters, running statistics calibrated on `calib` (so that the
    features of these inputs stay O(1) through ~40 random layers), then perturbed so that
    mean and variance really matter."""
    bns = [m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    for bn in bns:
        c = bn.num_features
        bn.weight.copy_(torch.rand(c, generator=gen) + 0.5)
        bn.bias.copy_(torch.rand(c, generator=gen) - 0.5)
        bn.reset_running_stats()
        bn.momentum = None  # cumulative average over the calibration pass
    model.train()
    model(calib)
    model.eval()
    for bn in bns:
        c = bn.num_features
        bn.running_mean.add_(0.2 * bn.running_var.sqrt() * torch.randn(c, generator=gen))
        bn.running_var.mul_(torch.exp(0.3 * torch.randn(c, generator=gen)))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("outdir")
    ap.add_argument("--weights-only", action="store_true")
    args = ap.parse_args()
    torch.manual_seed(0)
    torch.set_num_threads(2)
    gen = torch.Generator().manual_seed(1234)

    model = build_random_inception()
    inputs = {name: torch.rand(b, 3, h, w, generator=gen) * 2 - 1 for name, (b, h, w) in CASES.items()}
    if not args.weights_only:
        resized = [F.interpolate((x + 1) / 2, size=(299, 299), mode="bilinear", align_corners=False)
                   for x in inputs.values()]
        randomise_batchnorm(model, torch.cat(resized), gen)
    model.eval()
    state = {k: v.detach().contiguous() for k, v in model.state_dict().items() if v.is_floating_point()}
    os.makedirs(args.outdir, exist_ok=True)
    save_file(state, os.path.join(args.outdir, "weights.safetensors"))
    if args.weights_only:
        return

    out = {}
    with torch.no_grad():
        for name, x in inputs.items():
            feats = model((x + 1) / 2)[0].squeeze(-1).squeeze(-1)
            out[f"input.{name}"] = x.contiguous()
            out[f"expected.{name}"] = feats.contiguous()
    save_file(out, os.path.join(args.outdir, "case.safetensors"))


if __name__ == "__main__":
    main()
